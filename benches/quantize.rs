//! INT8 calibration statistics and the runtimes on float, INT8 (QDQ for ONNX Runtime,
//! QLinearConv for tract) and FP16 compiles of one model, in one run so the ratios compare.
//! `PDI_BENCH_MODEL=/path/full.onnx cargo bench --bench quantize` measures a full-size export;
//! the default is the trained tiny model.

use criterion::{criterion_group, criterion_main, Criterion};
use pdi_compile::onnx::proto::ModelProto;
use pdi_compile::pipeline::{run, PassContext, Recipe};
use pdi_compile::quant::histogram::Histogram;
use pdi_compile::quant::params::ActivationType;
use pdi_compile::quant::range::{choose, Method};
use pdi_compile::runtime::{self, Engine};
use pdi_compile::tensor::Tensor;
use std::path::PathBuf;

fn model_path() -> PathBuf {
    std::env::var_os("PDI_BENCH_MODEL")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/trained/pdinet_v5_tiny_trained.onnx"))
}

/// The lossless passes, then `last` (a quantize or fp16 step), on a few calibration frames.
fn compiled(original: &ModelProto, last: &str) -> ModelProto {
    let text = format!("name: bench\npasses: [strip-recon, {{bind-psf: {{psf: calib/single_lwir_blur.npy}}}}, fold-constants, fold-psf-gates, fold-bn, resize-to-deconv, dce, cleanup{last}]");
    let mut m = original.clone();
    std::env::set_current_dir(env!("CARGO_MANIFEST_DIR")).unwrap();
    run(&Recipe::parse(&text).unwrap(), &mut m, &mut PassContext::default()).unwrap();
    m
}

fn statistics(c: &mut Criterion) {
    // One 640x480 SiLU activation of 32 channels at stride 4: 614 400 values.
    let v: Vec<f32> = (0..32 * 120 * 160).map(|i| { let x = ((i * 7919) % 20_000) as f32 / 1000.0 - 4.0; x / (1.0 + (-x).exp()) }).collect();
    let mut g = c.benchmark_group("quant/statistics");
    g.bench_function("histogram 614k values", |b| b.iter(|| { let mut h = Histogram::default(); h.add(&v); h }));
    let mut h = Histogram::default();
    h.add(&v);
    for m in [Method::Minmax, Method::Percentile, Method::Entropy, Method::Mse] {
        g.bench_function(format!("range {m:?}"), |b| b.iter(|| choose(&h, m, 99.99, ActivationType::U8)));
    }
    g.finish();
}

fn runtimes(c: &mut Criterion) {
    let path = model_path();
    let original = pdi_compile::onnx::load(&path).unwrap().model;
    let quick = "calib_frames: 8, analysis_frames: 1, held_out_frames: 1";
    let variants = [
        ("f32", compiled(&original, "")),
        ("int8-qdq", compiled(&original, &format!(", {{quantize: {{weight_bits: 7, {quick}}}}}"))),
        ("int8-qlinear", compiled(&original, &format!(", {{quantize: {{weight_bits: 7, format: qlinear, {quick}}}}}"))),
        ("fp16", compiled(&original, ", {fp16: {calib_frames: 2}}")),
    ];
    let g0 = variants[0].1.graph.as_ref().unwrap();
    let input = g0.input.iter().find(|v| !g0.initializer.iter().any(|t| t.name == v.name)).unwrap();
    let shape = pdi_compile::ir::shapes::declared(input).static_shape().unwrap();
    let frame = pdi_compile::calib_frames::calibration_frames(None, 1, shape[2], shape[3], 0).unwrap().frames.remove(0).image;
    let feeds: Vec<(String, Tensor)> = vec![(input.name.clone(), frame)];
    let mut g = c.benchmark_group(format!("runtimes/{}", path.file_stem().unwrap().to_string_lossy()));
    g.sample_size(10);
    for (name, m) in &variants {
        for engine in [Engine::Ort, Engine::Tract] {
            let mut rt = runtime::load(engine, m, &feeds, runtime::all_cores()).unwrap();
            g.bench_function(format!("{name}/{engine:?}"), |b| b.iter(|| rt.run(&feeds).unwrap()));
        }
    }
    g.finish();
}

criterion_group!(benches, statistics, runtimes);
criterion_main!(benches);
