//! Load, save and inspect speed. `PDI_BENCH_MODEL=/path/full.onnx cargo bench --bench io`
//! measures a full-size export (made by models/pdinet/export.py); the default is a fixture.

use criterion::{criterion_group, criterion_main, Criterion};
use prost::Message;
use std::path::PathBuf;

fn model_path() -> PathBuf {
    std::env::var_os("PDI_BENCH_MODEL")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models/fixtures/pdinet_v5_input_op17_nofold.onnx"))
}

fn io(c: &mut Criterion) {
    let path = model_path();
    let bytes = std::fs::read(&path).expect("benchmark model");
    let model = pdi_compile::onnx::load_bytes(&bytes, path.parent()).unwrap().model;
    let dir = tempfile::tempdir().unwrap();
    let mut g = c.benchmark_group(format!("io/{}MB", bytes.len() >> 20));
    g.sample_size(10);
    g.bench_function("decode", |b| b.iter(|| pdi_compile::onnx::load_bytes(&bytes, path.parent()).unwrap()));
    g.bench_function("encode", |b| b.iter(|| model.encode_to_vec()));
    g.bench_function("save", |b| b.iter(|| pdi_compile::onnx::save(&model, &dir.path().join("m.onnx")).unwrap()));
    g.bench_function("inspect", |b| b.iter(|| pdi_compile::inspect::inspect(&model).unwrap()));
    g.finish();
}

criterion_group!(benches, io);
criterion_main!(benches);
