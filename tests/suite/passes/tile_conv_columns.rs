//! `tile-conv-columns`: the named convolutions become column tiles at most 127 wide,
//! computing the same products.

use super::*;
use pdi_compile::onnx::tensor_proto::to_tensor;

/// Convolutions tract would run as its direct spatial convolution, in the geometries a column
/// tiling has to respect: same padding with a bias, stride 2 with dilation 2 and uneven
/// padding, and one (stride 3) whose output rows are too short to need it.
fn direct_conv_chain() -> ModelProto {
    use pdi_compile::onnx::attr::{make_ints, make_int};
    let mut rng = crate::common::Lcg(11);
    let mut w = |name: &str, o: usize, c: usize| init(name, vec![o, c, 3, 3], (0..o * c * 9).map(|_| rng.next_f32() - 0.5).collect());
    let conv = |pads: Vec<i64>, stride: i64, dilation: i64| vec![make_int("group", 1), make_ints("kernel_shape", vec![3, 3]), make_ints("pads", pads), make_ints("strides", vec![stride; 2]), make_ints("dilations", vec![dilation; 2])];
    ModelProto {
        ir_version: 8,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
        graph: Some(GraphProto {
            node: vec![
                node("Conv", &["x", "wa", "ba"], "a", conv(vec![1; 4], 1, 1)),
                node("Conv", &["a", "wb"], "b", conv(vec![2, 2, 1, 1], 2, 2)),
                node("Conv", &["b", "wc"], "y", conv(vec![1; 4], 1, 1)),
                node("Conv", &["x", "wd"], "z", conv(vec![1; 4], 3, 1)),
            ],
            input: vec![vi("x", &[1, 3, 9, 301])],
            output: vec![vi("y", &[1, 4, 4, 150]), vi("z", &[1, 4, 3, 101])],
            initializer: vec![w("wa", 8, 3), init("ba", vec![8], (0..8).map(|i| i as f32 - 4.0).collect()), w("wb", 8, 8), w("wc", 4, 8), w("wd", 4, 3)],
            ..Default::default()
        }),
        ..Default::default()
    }
}

#[test]
fn conv_column_tiles_compute_the_same_on_ort_and_tract() {
    let mut m = direct_conv_chain();
    let inputs = vec![input("x", vec![1, 3, 9, 301], 5)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let reports = run_passes(&mut m, "{tile-conv-columns: {nodes: [a, b, y, z, nowhere]}}");
    let d = &reports[0].details;
    let tiles: Vec<u64> = d["tiled"].as_array().unwrap().iter().map(|t| t["tiles"].as_u64().unwrap()).collect();
    assert_eq!(tiles, [3, 3, 2], "{d}");
    let reasons: Vec<&str> = d["left"].as_array().unwrap().iter().map(|l| l["reason"].as_str().unwrap()).collect();
    assert!(reasons[0].contains("101 wide") && reasons[1].contains("not a float group-1"), "{d}");
    let g = m.graph.as_ref().unwrap();
    let widths: Vec<i64> = g.node.iter().filter(|n| n.op_type == "Slice").map(|n| {
        let at = |i: usize| to_tensor(g.initializer.iter().find(|t| t.name == n.input[i]).unwrap()).unwrap().as_i64s().unwrap()[0];
        at(2) - at(1)
    }).collect();
    assert!(widths.len() == 8 && widths.iter().all(|&w| w <= 127), "{widths:?}");
    assert_float_noise_on_ort_and_tract(&before, &m, &inputs);
}
