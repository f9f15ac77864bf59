//! `split-wide-depthwise`: depthwise convolutions wider than tract's SIMD kernel become bands
//! it vectorizes, computing the same sums.

use super::*;

/// Depthwise convolutions wider than tract's SIMD kernel takes, in the geometries a split has
/// to respect: same padding with a bias, stride 2 on a 17x17 kernel (no row band fits, so
/// rows and columns split), dilation 2, and no padding at all (cannot split).
fn wide_depthwise_chain() -> ModelProto {
    let mut rng = crate::common::Lcg(7);
    let mut w = |name: &str, k: usize| init(name, vec![3, 1, k, k], (0..3 * k * k).map(|_| rng.next_f32() - 0.5).collect());
    let dw = |pads: i64, stride: i64, dilation: i64, k: i64| {
        use pdi_compile::onnx::attr::{make_int, make_ints};
        vec![make_int("group", 3), make_ints("kernel_shape", vec![k, k]), make_ints("pads", vec![pads; 4]), make_ints("strides", vec![stride; 2]), make_ints("dilations", vec![dilation; 2])]
    };
    ModelProto {
        ir_version: 8,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
        graph: Some(GraphProto {
            node: vec![
                node("Conv", &["x", "wa", "ba"], "a", dw(7, 1, 1, 15)),
                node("Conv", &["a", "wb"], "b", dw(8, 2, 1, 17)),
                node("Conv", &["b", "wc"], "y", dw(14, 1, 2, 15)),
                node("Conv", &["x", "wd"], "z", dw(0, 1, 1, 15)),
            ],
            input: vec![vi("x", &[1, 3, 20, 24])],
            output: vec![vi("y", &[1, 3, 10, 12]), vi("z", &[1, 3, 6, 10])],
            initializer: vec![w("wa", 15), init("ba", vec![3], vec![0.5, -1.0, 2.0]), w("wb", 17), w("wc", 15), w("wd", 15)],
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[test]
fn wide_depthwise_splits_into_bands_tract_vectorizes_and_computes_the_same() {
    let mut m = wide_depthwise_chain();
    let inputs = vec![input("x", vec![1, 3, 20, 24], 3)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let reports = run_passes(&mut m, "split-wide-depthwise");
    let d = &reports[0].details;
    let bands: Vec<usize> = d["split"].as_array().unwrap().iter().map(|s| s["bands"].as_array().unwrap().len()).collect();
    assert_eq!(bands, [2, 4, 2], "{d}");
    assert!(d["left"][0]["reason"].as_str().unwrap().contains("non-negative"), "{d}");
    let g = m.graph.as_ref().unwrap();
    for n in g.node.iter().filter(|n| n.op_type == "Conv" && n.output[0] != "z") {
        let k = pdi_compile::onnx::attr::ints(n, "kernel_shape").unwrap();
        assert!(k[0] * k[1] <= 128, "{} keeps {k:?}", n.name);
    }
    // Another order of the same float sums: float noise, on ORT and on tract.
    assert_float_noise_on_ort_and_tract(&before, &m, &inputs);
}
