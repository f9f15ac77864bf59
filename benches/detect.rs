//! Decode + NMS, the post-processing `run` and the `deploy::Detector` do after every
//! inference: on the trained width-0.25 v5's real output for a simulated frame, at the
//! deployment threshold (0.25) and at validation's (0.001, where mAP is computed).

use criterion::{criterion_group, criterion_main, Criterion};
use pdi_compile::deploy::{Detector, Image, Options};
use std::path::PathBuf;

fn decode_nms(c: &mut Criterion) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let opts = Options { psf: Some(root.join("calib/single_lwir_blur.npy")), threads: Some(1), ..Options::default() };
    let mut d = Detector::load_with(&root.join("models/trained/pdinet_v5_w0.25_trained.onnx"), &opts).unwrap();
    let (h, w) = d.frame_size();
    let f = &pdi_compile::frames::synthetic(1, h, w, 3)[0];
    let frame = Image { width: w, height: h, data: f.image.as_f32().unwrap().to_vec(), bits: 16 };
    let out = d.infer(&frame).unwrap();
    let mut g = c.benchmark_group("detect/v5-w0.25-256x192");
    for conf in [0.25f32, 0.001] {
        let n = d.detections(&out, conf).unwrap().len();
        g.bench_function(format!("decode+nms conf {conf} ({n} kept)"), |b| b.iter(|| d.detections(&out, conf).unwrap()));
    }
    g.finish();
}

criterion_group!(benches, decode_nms);
criterion_main!(benches);
