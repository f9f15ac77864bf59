//! `fp16`: half-precision weights and activations, with the decode and the interface in
//! float32, on both runtimes.

use super::quantize::{compile, run_candidate, TINY, V8};
use crate::common::*;
use pdi_compile::runtime::Engine;

/// FP16 of the trained model (close to float: 2e-3) and of a random-weight v8 fixture (which
/// amplifies f16 rounding through activations of +-200: 0.1).
#[test]
fn fp16_runs_on_both_runtimes_with_the_decode_in_f32() {
    let dir = tempfile::tempdir().unwrap();
    for (fixture, bound) in [(TINY, 2e-3), (V8, 0.1)] {
        let f32_out = dir.path().join("f32");
        compile(fixture, "passes/detect-f32.yaml", &f32_out, &[]);
        let out = dir.path().join("fp16");
        let r = compile(fixture, "passes/detect-fp16.yaml", &out, &[]);
        assert!(r["nodes_f16"].as_u64().unwrap() > 20, "{r}");
        assert!(r["nodes_f32"].to_string().contains("decode"), "{r}");
        let reference = run_candidate(&f32_out.join("model.onnx"), Engine::Ort);
        for engine in [Engine::Ort, Engine::Tract] {
            let got = run_candidate(&out.join("model.onnx"), engine);
            for ((name, a), (_, b)) in reference.iter().zip(&got) {
                assert_eq!(a.shape, b.shape);
                assert_eq!(b.dtype(), pdi_compile::tensor::DType::F32, "outputs stay float32");
                let e = rel_l2(a, b);
                println!("{fixture} fp16 {engine:?} {name}: rel L2 {e:.2e}");
                assert!(e < bound, "{fixture} {engine:?} {name}: {e}");
            }
        }
    }
}
