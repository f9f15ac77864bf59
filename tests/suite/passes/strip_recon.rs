//! `strip-recon`: the frame-sized (reconstruction) output and the nodes only it needed go; the
//! detection output is computed exactly as before. Without a frame-sized output every output
//! stays, with a warning.

use super::*;
use pdi_compile::onnx::attr::{make_int, make_ints};

/// x -> a (shared encoder) -> recon (frame-sized, the decoder) and -> det (stride 2, the head).
fn two_branches() -> ModelProto {
    let mut rng = crate::common::Lcg(9);
    let mut w = |name: &str, shape: Vec<usize>| {
        let n = shape.iter().product();
        init(name, shape, (0..n).map(|_| rng.next_f32() - 0.5).collect())
    };
    let conv = |k: i64, s: i64| vec![make_ints("kernel_shape", vec![k, k]), make_ints("pads", vec![k / 2; 4]), make_ints("strides", vec![s, s]), make_int("group", 1)];
    model(
        vec![
            node("Conv", &["x", "wa"], "a", conv(3, 1)),
            node("Relu", &["a"], "ar", vec![]),
            node("Conv", &["ar", "wr"], "r1", conv(3, 1)),
            node("Conv", &["r1", "wr2"], "recon", conv(1, 1)),
            node("Conv", &["ar", "wd"], "det", conv(3, 2)),
        ],
        vec![vi("x", &[1, 1, 8, 8])],
        vec![vi("recon", &[1, 1, 8, 8]), vi("det", &[1, 3, 4, 4])],
        vec![w("wa", vec![2, 1, 3, 3]), w("wr", vec![2, 2, 3, 3]), w("wr2", vec![1, 2, 1, 1]), w("wd", vec![3, 2, 3, 3])],
    )
}

#[test]
fn the_decoder_goes_and_the_detection_output_stays_bit_identical() {
    let mut m = two_branches();
    let inputs = vec![input("x", vec![1, 1, 8, 8], 2)];
    let before: Vec<_> = outputs(Engine::Ort, &m, &inputs).into_iter().filter(|(n, _)| n == "det").collect();
    let r = run_passes(&mut m, "strip-recon");
    assert_eq!(r[0].details["outputs_removed"], serde_json::json!(["recon"]), "{}", r[0].details);
    assert_eq!(ops(&m), ["Conv", "Relu", "Conv"], "the decoder's two convolutions are gone");
    assert_eq!(m.graph.as_ref().unwrap().initializer.len(), 2, "its weights too");
    assert_same(&before, &outputs(Engine::Ort, &m, &inputs), 0.0);
}

#[test]
fn without_a_frame_sized_output_everything_stays_with_a_warning() {
    let mut m = two_branches();
    let g = m.graph.as_mut().unwrap();
    g.output.retain(|o| o.name == "det");
    let mut cx = PassContext::default();
    let r = run_with(&mut m, "strip-recon, dce", &mut cx);
    assert_eq!(r[0].details["outputs_kept"], serde_json::json!(["det"]));
    assert_eq!(ops(&m), ["Conv", "Relu", "Conv"]);
    assert!(r[0].warnings.len() == 1 && r[0].warnings[0].starts_with("strip-recon: no output is frame-sized"), "{:?}", r[0].warnings);
    assert_eq!(cx.warnings, r[0].warnings);
}
