//! Passes on small hand-built graphs: the edge cases fixtures do not reach.

use crate::common;
use pdi_compile::onnx::proto::*;
use pdi_compile::onnx::tensor_proto::{from_tensor, to_tensor};
use pdi_compile::pipeline::{self, PassContext, Recipe};
use pdi_compile::runtime::{self, Engine};
use pdi_compile::tensor::Tensor;

fn vi(name: &str, dims: &[i64]) -> ValueInfoProto {
    let dim = dims.iter().map(|&d| Dimension { value: Some(DimensionValue::DimValue(d)), denotation: String::new() }).collect();
    ValueInfoProto { name: name.into(), r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: Some(TensorShapeProto { dim }) })), denotation: String::new() }), ..Default::default() }
}

fn node(op: &str, inputs: &[&str], output: &str, attrs: Vec<AttributeProto>) -> NodeProto {
    NodeProto { op_type: op.into(), name: output.into(), input: inputs.iter().map(|s| s.to_string()).collect(), output: vec![output.into()], attribute: attrs, ..Default::default() }
}

fn init(name: &str, shape: Vec<usize>, v: Vec<f32>) -> TensorProto {
    from_tensor(name, &Tensor::f32(shape, v))
}

/// x -> Conv(2->2, 1x1) -> BN(var = [0, 1e-30], eps) -> Identity -> y, plus a duplicate initializer.
fn conv_bn(eps: f32) -> ModelProto {
    let eps_attr = AttributeProto { name: "epsilon".into(), r#type: AttributeType::Float as i32, f: Some(eps), ..Default::default() };
    ModelProto {
        ir_version: 8,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
        graph: Some(GraphProto {
            node: vec![
                node("Conv", &["x", "w"], "c", vec![]),
                node("BatchNormalization", &["c", "gamma", "beta", "mean", "var"], "b", vec![eps_attr]),
                node("Identity", &["b"], "i", vec![]),
                node("Add", &["i", "beta_copy"], "y", vec![]),
            ],
            input: vec![vi("x", &[1, 2, 3, 3])],
            output: vec![vi("y", &[1, 2, 3, 3])],
            initializer: vec![
                init("w", vec![2, 2, 1, 1], vec![1.0, 2.0, -1.0, 0.5]),
                init("gamma", vec![2], vec![1.5, 2.0]),
                init("beta", vec![2], vec![0.1, -0.2]),
                init("beta_copy", vec![2, 1, 1], vec![0.1, -0.2]),
                init("dup", vec![2, 1, 1], vec![0.1, -0.2]),
                init("mean", vec![2], vec![0.3, 0.0]),
                init("var", vec![2], vec![0.0, 1e-30]),
            ],
            ..Default::default()
        }),
        ..Default::default()
    }
}

fn run_pipeline(model: &mut ModelProto, passes: &str) -> Vec<pipeline::PassReport> {
    let recipe = Recipe::parse(&format!("name: t\npasses: [{passes}]\n")).unwrap();
    pipeline::run(&recipe, model, &mut PassContext::default()).unwrap()
}

fn output(model: &ModelProto) -> Tensor {
    let x = Tensor::f32(vec![1, 2, 3, 3], (0..18).map(|i| i as f32 * 0.1 - 0.7).collect());
    let inputs = vec![("x".to_string(), x)];
    runtime::load(Engine::Ort, model, &inputs, 1).unwrap().run(&inputs).unwrap().remove(0).1
}

#[test]
fn bn_with_tiny_variance_folds_when_eps_keeps_it_finite() {
    let mut m = conv_bn(1e-5);
    let before = output(&m);
    let reports = run_pipeline(&mut m, "fold-bn, cleanup, dce");
    assert_eq!(reports[0].details["folded_into_conv"], 1, "{}", reports[0].details);
    let ops: Vec<&str> = m.graph.as_ref().unwrap().node.iter().map(|n| n.op_type.as_str()).collect();
    assert_eq!(ops, ["Conv", "Add"], "BN folded, Identity bypassed");
    let e = common::rel_l2(&before, &output(&m));
    assert!(e < 1e-6, "rel L2 {e:e}");
}

#[test]
fn bn_with_zero_variance_and_eps_is_left_and_named() {
    let mut m = conv_bn(0.0);
    let reports = run_pipeline(&mut m, "fold-bn");
    let left = reports[0].details["left"].as_array().unwrap();
    assert_eq!(left.len(), 1);
    assert!(left[0]["reason"].as_str().unwrap().contains("infinite"), "{}", left[0]);
    assert!(m.graph.as_ref().unwrap().node.iter().any(|n| n.op_type == "BatchNormalization"));
}

#[test]
fn cleanup_merges_duplicate_initializers() {
    let mut m = conv_bn(1e-5);
    m.graph.as_mut().unwrap().node[3].input[1] = "dup".into();
    m.graph.as_mut().unwrap().node.push(node("Mul", &["y", "beta_copy"], "z", vec![]));
    m.graph.as_mut().unwrap().output = vec![vi("z", &[1, 2, 3, 3])];
    let before = output(&m);
    let reports = run_pipeline(&mut m, "cleanup");
    assert_eq!(reports[0].details["initializers_merged"], 1, "{}", reports[0].details);
    assert!(before.bit_identical(&output(&m)));
    let names: Vec<&str> = m.graph.as_ref().unwrap().initializer.iter().map(|t| t.name.as_str()).collect();
    assert!(!(names.contains(&"dup") && names.contains(&"beta_copy")), "{names:?}");
    let _ = to_tensor(&m.graph.as_ref().unwrap().initializer[0]).unwrap();
}

/// Depthwise convolutions wider than tract's SIMD kernel takes, in the geometries a split has
/// to respect: same padding with a bias, stride 2 on a 17x17 kernel (no row band fits, so
/// rows and columns split), dilation 2, and no padding at all (cannot split).
fn wide_depthwise_chain() -> ModelProto {
    let mut rng = common::Lcg(7);
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
    let mut rng = common::Lcg(3);
    let inputs = vec![("x".to_string(), Tensor::f32(vec![1, 3, 20, 24], (0..3 * 480).map(|_| rng.next_f32()).collect()))];
    let before = runtime::load(Engine::Ort, &m, &inputs, 1).unwrap().run(&inputs).unwrap();
    let reports = run_pipeline(&mut m, "split-wide-depthwise");
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

/// Convolutions tract would run as its direct spatial convolution, in the geometries a column
/// tiling has to respect: same padding with a bias, stride 2 with dilation 2 and uneven
/// padding, and one (stride 3) whose output rows are too short to need it.
fn direct_conv_chain() -> ModelProto {
    use pdi_compile::onnx::attr::{make_ints, make_int};
    let mut rng = common::Lcg(11);
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
    let mut rng = common::Lcg(5);
    let inputs = vec![("x".to_string(), Tensor::f32(vec![1, 3, 9, 301], (0..3 * 9 * 301).map(|_| rng.next_f32()).collect()))];
    let before = runtime::load(Engine::Ort, &m, &inputs, 1).unwrap().run(&inputs).unwrap();
    let reports = run_pipeline(&mut m, "{tile-conv-columns: {nodes: [a, b, y, z, nowhere]}}");
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

/// `m` on ONNX Runtime and on tract gives `before` (the outputs before a rewrite, on ORT)
/// within float noise: rel L2 below 1e-6 on every output.
fn assert_float_noise_on_ort_and_tract(before: &[(String, Tensor)], m: &ModelProto, inputs: &[(String, Tensor)]) {
    for engine in [Engine::Ort, Engine::Tract] {
        let after = runtime::load(engine, m, inputs, 1).unwrap().run(inputs).unwrap();
        for ((name, a), (_, b)) in before.iter().zip(after) {
            let e = common::rel_l2(a, &b);
            assert!(e < 1e-6, "{name} on {engine:?}: rel L2 {e:e}");
        }
    }
}

/// Every shipped recipe reads, names itself after its file, and each of its passes accepts
/// its options (unknown ones are errors), so a recipe is never first found broken by a user.
#[test]
fn every_shipped_recipe_builds() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("passes");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "yaml") || ["gate.yaml", "stress.yaml"].iter().any(|n| path.ends_with(n)) {
            continue;
        }
        let recipe = Recipe::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        assert_eq!(Some(recipe.name.as_str()), path.file_stem().and_then(|s| s.to_str()), "{}", path.display());
        for spec in &recipe.passes {
            if let Err(e) = pipeline::build_pass(spec) {
                panic!("{}: pass {}: {e:#}", path.display(), spec.name);
            }
        }
        seen += 1;
    }
    assert!(seen >= 18, "only {seen} recipes in {}", dir.display());
}
