//! Degradation speed: one 640x480 frame through 48 field PSFs of 31x31 (target: <= 30 ms
//! median on the 2-core CI machine), plus PSF simulation and scene synthesis.

use criterion::{criterion_group, criterion_main, Criterion};
use pdi_compile::optics::degrade::{add_noise, NoiseModel, SpatialBlur, FULL_SCALE_14BIT};
use pdi_compile::optics::lens::Lens;
use pdi_compile::optics::psf::simulate;
use pdi_compile::optics::rng::Rng;
use pdi_compile::optics::synth;
use std::path::PathBuf;

fn bench(c: &mut Criterion) {
    let lens = Lens::load(&PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("calib/lens_single_lwir.yaml")).unwrap();
    let (_, kernels) = simulate(&lens, 6, 8, 31);
    let blur = SpatialBlur::new(&kernels, 31, 6, 8, 480, 640);
    let scene = synth::scene(640, 480, 1);
    let noise = NoiseModel { q: 90.0, sigma: 2.0, full_scale: FULL_SCALE_14BIT };
    let mut g = c.benchmark_group("optics");
    g.sample_size(30);
    g.bench_function("degrade_640x480_48psf_31x31", |b| {
        b.iter(|| {
            let mut out = blur.apply(&scene.pixels);
            add_noise(&mut out, &noise, &mut Rng::new(1));
            out
        })
    });
    g.bench_function("psf_simulate_6x8_31x31", |b| b.iter(|| simulate(&lens, 6, 8, 31)));
    g.bench_function("synth_scene_640x480", |b| b.iter(|| synth::scene(640, 480, 7)));
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
