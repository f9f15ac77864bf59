//! `space-to-depth`: a narrow block at full resolution (convolutions, activations, a 2x2 max
//! pooling) runs on 2x2 pixel blocks and computes the same; every later pass and tract get it
//! back as it was, byte for byte; INT8 quantizes the block in its wide form and takes the
//! pooling's maximum on the integer codes.

use super::*;
use pdi_compile::onnx::attr::make_ints;

/// A 2 -> 4 convolution (3x3, bias) and Relu, a 4 -> 3 one (5x5, no bias) and LeakyRelu, a 2x2
/// max pooling, then a 1x1 convolution after the block. `height` x `width` input; `r_out`
/// makes the first Relu's output a graph output as well.
fn block(height: i64, width: i64, r_out: bool) -> ModelProto {
    let mut rng = crate::common::Lcg(5);
    let mut w = |name: &str, shape: Vec<usize>| {
        let n = shape.iter().product();
        init(name, shape, (0..n).map(|_| rng.next_f32() - 0.5).collect())
    };
    let conv = |k: i64| vec![make_ints("kernel_shape", vec![k, k]), make_ints("pads", vec![k / 2; 4]), make_ints("strides", vec![1, 1])];
    let pool = vec![make_ints("kernel_shape", vec![2, 2]), make_ints("strides", vec![2, 2])];
    let mut outputs = vec![vi("d", &[1, 8, height / 2, width / 2])];
    if r_out {
        outputs.push(vi("r", &[1, 4, height, width]));
    }
    model(
        vec![
            node("Conv", &["x", "wa", "ba"], "a", conv(3)),
            node("Relu", &["a"], "r", vec![]),
            node("Conv", &["r", "wb"], "b", conv(5)),
            node("LeakyRelu", &["b"], "c", vec![]),
            node("MaxPool", &["c"], "p", pool),
            node("Conv", &["p", "wd"], "d", conv(1)),
        ],
        vec![vi("x", &[1, 2, height, width])],
        outputs,
        vec![w("wa", vec![4, 2, 3, 3]), init("ba", vec![4], vec![0.25, -0.5, 0.1, 0.0]), w("wb", vec![3, 4, 5, 5]), w("wd", vec![8, 3, 1, 1])],
    )
}

#[test]
fn a_narrow_block_runs_on_pixel_blocks_and_computes_the_same() {
    let original = block(12, 16, false);
    let mut m = original.clone();
    let inputs = vec![input("x", vec![1, 2, 12, 16], 3)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let reports = run_passes(&mut m, "space-to-depth");
    assert_eq!(reports[0].details["rewritten"], serde_json::json!([{
        "pool": "p",
        "convolutions": [{ "node": "a", "channels": [2, 4] }, { "node": "b", "channels": [4, 3] }],
        "input": [1, 2, 12, 16],
    }]));
    assert_eq!(ops(&m), ["SpaceToDepth", "Conv", "Relu", "Conv", "LeakyRelu", "Split", "Max", "Conv"]);
    let g = m.graph.as_ref().unwrap();
    let dims = |n: usize| g.initializer.iter().find(|t| t.name == g.node[n].input[1]).unwrap().dims.clone();
    // 3x3 and 5x5 kernels both span 3x3 blocks; four pixel positions in and out.
    assert_eq!((dims(1), dims(3)), (vec![16, 8, 3, 3], vec![12, 16, 3, 3]));
    assert_eq!(pdi_compile::onnx::attr::ints(&g.node[3], "pads").unwrap(), [1, 1, 1, 1]);
    assert_eq!((g.node[6].name.as_str(), g.node[6].output[0].as_str()), ("p", "p"));
    assert_float_noise_on_ort_and_tract(&before, &m, &inputs);

    // tract is given the block as it was.
    let mut for_tract = m.clone();
    pdi_compile::runtime::tract_runtime::make_tract_ready(for_tract.graph.as_mut().unwrap()).unwrap();
    assert_eq!(ops(&for_tract), ops(&original));

    // Any later pass gets the block back under its own names: the same bytes as that pass on
    // the original.
    assert_later_passes_get_the_original(&original, &m, "space-to-depth");
}

#[test]
fn a_block_starts_where_a_value_has_other_readers_and_odd_sizes_or_wide_layers_are_left_alone() {
    // The first Relu's output is also a graph output: the block is the second convolution on.
    let mut m = block(12, 16, true);
    let inputs = vec![input("x", vec![1, 2, 12, 16], 4)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let reports = run_passes(&mut m, "space-to-depth");
    assert_eq!(reports[0].details["rewritten"][0]["convolutions"], serde_json::json!([{ "node": "b", "channels": [4, 3] }]));
    assert_eq!(ops(&m), ["Conv", "Relu", "SpaceToDepth", "Conv", "LeakyRelu", "Split", "Max", "Conv"]);
    assert_float_noise_on_ort_and_tract(&before, &m, &inputs);

    for (mut m, passes) in [(block(12, 15, false), "space-to-depth"), (block(12, 16, false), "{space-to-depth: {max_channels: 3}}")] {
        let was = m.clone();
        let reports = run_passes(&mut m, passes);
        assert_eq!(reports[0].details["rewritten"], serde_json::json!([]), "{passes}");
        assert_eq!(m, was);
    }
    let mut m = block(12, 16, false);
    let e = Recipe::parse("name: t\npasses: [{space-to-depth: {max_channels: 0}}]\n").and_then(|r| pipeline::run(&r, &mut m, &mut PassContext::default())).err().expect("max_channels: 0 is refused");
    assert!(format!("{e:#}").contains("max_channels must be 1 to 1024"), "{e:#}");
}

/// On the trained tiny model, `detect-int8` (which runs this pass before `quantize`) quantizes
/// the encoder's first block in its wide form: more integer convolutions than the recipe
/// without the pass, the pooling's Max on the codes (a QuantizeLinear before each input, a
/// DequantizeLinear after), and outputs as close to float.
#[test]
fn int8_quantizes_the_wide_block_and_takes_the_maximum_on_codes() {
    use super::quantize::{compile, TINY};
    let dir = tempfile::tempdir().unwrap();
    let with = dir.path().join("with.yaml");
    std::fs::write(&with, crate::common::recipe_edit("passes/detect-int8.yaml", "calib_frames: 64", "calib_frames: 16")).unwrap();
    let without = dir.path().join("without.yaml");
    std::fs::write(&without, crate::common::recipe_edit(with.to_str().unwrap(), crate::common::SPACE_TO_DEPTH, "")).unwrap();
    let q_with = compile(TINY, with.to_str().unwrap(), &dir.path().join("with"), &[]);
    let q_without = compile(TINY, without.to_str().unwrap(), &dir.path().join("without"), &[]);
    let integer = |q: &serde_json::Value| q["ort_optimized_ops"]["QLinearConv"].as_u64().unwrap_or(0);
    println!("QLinearConv {} with, {} without; worst rel L2 {} with, {} without", integer(&q_with), integer(&q_without), q_with["worst_output_rel_l2"], q_without["worst_output_rel_l2"]);
    assert!(integer(&q_with) >= integer(&q_without) + 2, "the block's two convolutions run in integers");
    let m = crate::common::load(&dir.path().join("with/model.onnx"));
    let g = m.graph.as_ref().unwrap();
    let producer = |v: &str| g.node.iter().find(|n| n.output.iter().any(|o| o == v)).map(|n| n.op_type.as_str());
    let maxes: Vec<&NodeProto> = g.node.iter().filter(|n| n.op_type == "Max").collect();
    assert!(!maxes.is_empty() && q_with["emitted"]["on_codes"].as_u64() == Some(maxes.len() as u64), "{}", q_with["emitted"]);
    for max in maxes {
        assert!(max.input.iter().all(|v| producer(v) == Some("QuantizeLinear")), "Max reads codes");
        assert!(g.node.iter().filter(|n| n.input.contains(&max.output[0])).all(|n| n.op_type == "DequantizeLinear"), "Max writes codes");
    }
    let (w, wo) = (q_with["worst_output_rel_l2"].as_f64().unwrap(), q_without["worst_output_rel_l2"].as_f64().unwrap());
    assert!(w <= 0.1 && w <= wo * 1.5 + 0.01, "with the block quantized: rel L2 {w} (without: {wo})");
}
