//! `narrow-convs-nchw`: group-1 convolutions narrower than ONNX Runtime's NCHWc block become
//! 3-D convolutions over a unit axis, or (`form: bias`) read their bias through a
//! DequantizeLinear, computing the same sums; every later pass and tract get them back as
//! they were, byte for byte.

use super::*;
use pdi_compile::onnx::attr::{make_int, make_ints};
use pdi_compile::runtime::ort_runtime::OrtRuntime;

/// A 4 -> 2 convolution with a bias and a Relu, a 2 -> 8 one with stride 2 whose output is
/// also a graph output, an 8 -> 16 one (not narrow: 16 outputs) and an 8-channel depthwise
/// one (group 8: ONNX Runtime keeps it in NCHW already).
fn narrow_chain() -> ModelProto {
    let mut rng = crate::common::Lcg(11);
    let mut w = |name: &str, shape: Vec<usize>| {
        let n = shape.iter().product();
        init(name, shape, (0..n).map(|_| rng.next_f32() - 0.5).collect())
    };
    let conv = |k: i64, pad: i64, stride: i64| vec![make_ints("kernel_shape", vec![k, k]), make_ints("pads", vec![pad; 4]), make_ints("strides", vec![stride; 2])];
    let mut dw = conv(3, 1, 1);
    dw.push(make_int("group", 8));
    model(
        vec![
            node("Conv", &["x", "wa", "ba"], "a", conv(3, 1, 1)),
            node("Relu", &["a"], "r", vec![]),
            node("Conv", &["r", "wb"], "b", conv(3, 1, 2)),
            node("Conv", &["b", "wc"], "c", conv(1, 0, 1)),
            node("Conv", &["b", "wd"], "d", dw),
        ],
        vec![vi("x", &[1, 4, 24, 32])],
        vec![vi("b", &[1, 8, 12, 16]), vi("c", &[1, 16, 12, 16]), vi("d", &[1, 8, 12, 16])],
        vec![w("wa", vec![2, 4, 3, 3]), init("ba", vec![2], vec![0.25, -0.5]), w("wb", vec![8, 2, 3, 3]), w("wc", vec![16, 8, 1, 1]), w("wd", vec![8, 1, 3, 3])],
    )
}

/// What the pass is for: ONNX Runtime's NCHWc transform no longer takes the rewritten
/// convolutions, so fewer reorders back to NCHW (x86 only: elsewhere ONNX Runtime has no
/// NCHWc layout).
fn assert_off_the_blocked_kernels(original: &ModelProto, m: &ModelProto) {
    if cfg!(target_arch = "x86_64") {
        let reorders = |m: &ModelProto| OrtRuntime::optimized_ops(m).unwrap().get("ReorderOutput").copied().unwrap_or(0);
        let (was, now) = (reorders(original), reorders(m));
        assert!(now < was, "ReorderOutput nodes: {was} before, {now} after");
    }
}

#[test]
fn narrow_convolutions_become_3d_and_compute_the_same() {
    let original = narrow_chain();
    let mut m = original.clone();
    let inputs = vec![input("x", vec![1, 4, 24, 32], 5)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let reports = run_passes(&mut m, "narrow-convs-nchw");
    let d = &reports[0].details;
    assert_eq!(d["rewritten"], serde_json::json!([
        { "node": "a", "channels": [4, 2], "form": "3d", "activation": "Relu" },
        { "node": "b", "channels": [2, 8], "form": "3d", "activation": null },
    ]));
    let g = m.graph.as_ref().unwrap();
    let ops: Vec<&str> = g.node.iter().map(|n| n.op_type.as_str()).collect();
    assert_eq!(ops, ["Unsqueeze", "Conv", "Relu", "Squeeze", "Unsqueeze", "Conv", "Squeeze", "Conv", "Conv"]);
    let a = &g.node[1];
    assert_eq!(g.initializer.iter().find(|t| t.name == a.input[1]).unwrap().dims, [2, 4, 1, 3, 3]);
    assert_eq!(pdi_compile::onnx::attr::ints(a, "pads").unwrap(), [0, 1, 1, 0, 1, 1]);
    assert_eq!(pdi_compile::onnx::attr::ints(&g.node[5], "strides").unwrap(), [1, 2, 2]);
    assert_float_noise_on_ort_and_tract(&before, &m, &inputs);

    assert_off_the_blocked_kernels(&original, &m);

    // Any later pass gets the 2-D convolutions back under their own names: the same bytes as
    // that pass on the original.
    assert_later_passes_get_the_original(&original, &m, "narrow-convs-nchw");
}

#[test]
fn with_form_bias_narrow_convolutions_stay_2d_off_the_blocked_kernels() {
    let original = narrow_chain();
    let mut m = original.clone();
    let inputs = vec![input("x", vec![1, 4, 24, 32], 5)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let reports = run_passes(&mut m, "{narrow-convs-nchw: {form: bias}}");
    assert_eq!(reports[0].details["rewritten"], serde_json::json!([
        { "node": "a", "channels": [4, 2], "form": "bias", "activation": null },
        { "node": "b", "channels": [2, 8], "form": "bias", "activation": null },
    ]));
    let g = m.graph.as_ref().unwrap();
    let ops: Vec<&str> = g.node.iter().map(|n| n.op_type.as_str()).collect();
    assert_eq!(ops, ["DequantizeLinear", "Conv", "Relu", "DequantizeLinear", "Conv", "Conv", "Conv"]);
    // The bias through codes of 1 and the bias itself as the scale; a zero bias where there
    // was none.
    let init = |name: &str| pdi_compile::onnx::tensor_proto::to_tensor(g.initializer.iter().find(|t| t.name == name).unwrap()).unwrap();
    assert_eq!(g.node[0].input[1], "ba");
    assert_eq!(init(&g.node[0].input[0]).data, pdi_compile::tensor::TensorData::I32(vec![1, 1]));
    assert_eq!(g.node[1].input[2], g.node[0].output[0]);
    assert_eq!(init(&g.node[3].input[1]).data, pdi_compile::tensor::TensorData::F32(vec![0.0; 8]));
    assert_float_noise_on_ort_and_tract(&before, &m, &inputs);
    // On ONNX Runtime, the same sums as the 3-D form, bit for bit: the same im2col order and
    // matrix product, and the bias a product by 1.
    let mut three_d = original.clone();
    run_passes(&mut three_d, "narrow-convs-nchw");
    for ((name, a), (_, b)) in outputs(Engine::Ort, &three_d, &inputs).iter().zip(outputs(Engine::Ort, &m, &inputs)) {
        assert_eq!(a, &b, "{name}");
    }

    assert_off_the_blocked_kernels(&original, &m);
    assert_later_passes_get_the_original(&original, &m, "narrow-convs-nchw");

    // Before opset 13 DequantizeLinear has no per-channel scale: the 3-D form instead.
    let mut old = narrow_chain();
    old.opset_import[0].version = 12;
    let reports = run_passes(&mut old, "{narrow-convs-nchw: {form: bias}}");
    assert_eq!(reports[0].details["rewritten"][0]["form"], "3d");
}

#[test]
fn wide_or_grouped_convolutions_and_bad_options_are_left_alone() {
    let mut m = narrow_chain();
    let reports = run_passes(&mut m, "{narrow-convs-nchw: {below: 2}}");
    assert_eq!(reports[0].details["rewritten"], serde_json::json!([]));
    assert_eq!(m, narrow_chain());
    let e = Recipe::parse("name: t\npasses: [{narrow-convs-nchw: {below: 1}}]\n").and_then(|r| pipeline::run(&r, &mut m, &mut PassContext::default())).err().expect("below: 1 is refused");
    assert!(format!("{e:#}").contains("below must be 2 to 4096 channels"), "{e:#}");
    let e = Recipe::parse("name: t\npasses: [{narrow-convs-nchw: {form: 2d}}]\n").and_then(|r| pipeline::run(&r, &mut m, &mut PassContext::default())).err().expect("form: 2d is refused");
    assert!(format!("{e:#}").contains("expected `3d` or `bias`"), "{e:#}");
}
