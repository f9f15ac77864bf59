//! One test file per pass (`src/passes/NAME.rs` → `tests/suite/passes/NAME.rs`), as TVM's
//! relax transforms have: the graph before and after, compared structurally, and the outputs
//! on ONNX Runtime. Small hand-built graphs where the pass is generic; the committed fixtures
//! and trained models where it needs PDI-Net's parts (the PALS-Bridge, a detection head).

use crate::common::{self, repo};
use pdi_compile::onnx::proto::*;
use pdi_compile::onnx::tensor_proto::from_tensor;
use pdi_compile::pipeline::{self, PassContext, Recipe};
use pdi_compile::runtime::{self, Engine};
use pdi_compile::tensor::Tensor;

mod bind_psf;
mod cleanup;
mod crop_roi;
mod dce;
mod drop_classes;
mod drop_strides;
mod example;
mod fold_bn;
mod fold_constants;
mod fold_psf_gates;
mod narrow_convs_nchw;
mod promote_constants;
mod prune;
mod quantize;
mod recover;
mod resize_to_deconv;
mod rknn_hybrid;
mod rknn_legalize;
mod rknn_qat;
mod space_to_depth;
mod split_wide_depthwise;
mod strip_recon;
mod tile_conv_columns;
mod to_fp16;

/// A float32 value declaration with a static shape.
pub fn vi(name: &str, dims: &[i64]) -> ValueInfoProto {
    let dim = dims.iter().map(|&d| Dimension { value: Some(DimensionValue::DimValue(d)), denotation: String::new() }).collect();
    ValueInfoProto { name: name.into(), r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: Some(TensorShapeProto { dim }) })), denotation: String::new() }), ..Default::default() }
}

/// A node named after its (single) output.
pub fn node(op: &str, inputs: &[&str], output: &str, attrs: Vec<AttributeProto>) -> NodeProto {
    NodeProto { op_type: op.into(), name: output.into(), input: inputs.iter().map(|s| s.to_string()).collect(), output: vec![output.into()], attribute: attrs, ..Default::default() }
}

/// A TENSOR attribute (a Constant's `value`).
pub fn tensor_attr(name: &str, t: &Tensor) -> AttributeProto {
    AttributeProto { name: name.into(), r#type: AttributeType::Tensor as i32, t: Some(from_tensor("", t)), ..Default::default() }
}

/// A STRING attribute.
pub fn string_attr(name: &str, s: &str) -> AttributeProto {
    AttributeProto { name: name.into(), r#type: AttributeType::String as i32, s: Some(s.as_bytes().to_vec()), ..Default::default() }
}

pub fn init(name: &str, shape: Vec<usize>, v: Vec<f32>) -> TensorProto {
    from_tensor(name, &Tensor::f32(shape, v))
}

/// An opset-17 model of `nodes`.
pub fn model(nodes: Vec<NodeProto>, inputs: Vec<ValueInfoProto>, outputs: Vec<ValueInfoProto>, initializer: Vec<TensorProto>) -> ModelProto {
    ModelProto {
        ir_version: 8,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
        graph: Some(GraphProto { node: nodes, input: inputs, output: outputs, initializer, ..Default::default() }),
        ..Default::default()
    }
}

/// Runs `passes` (a recipe's pass list, YAML flow style) on `model`.
pub fn run_passes(model: &mut ModelProto, passes: &str) -> Vec<pipeline::PassReport> {
    run_with(model, passes, &mut PassContext::default())
}

pub fn run_with(model: &mut ModelProto, passes: &str, cx: &mut PassContext) -> Vec<pipeline::PassReport> {
    let recipe = Recipe::parse(&format!("name: t\npasses: [{passes}]\n")).unwrap();
    pipeline::run(&recipe, model, cx).unwrap_or_else(|e| panic!("{passes}: {e:#}"))
}

/// The op types of a model's nodes, in order: the structural "after" a test compares.
pub fn ops(m: &ModelProto) -> Vec<String> {
    m.graph.as_ref().unwrap().node.iter().map(|n| n.op_type.clone()).collect()
}

/// Deterministic values in [0, 1) for an input of `shape`.
pub fn input(name: &str, shape: Vec<usize>, seed: u64) -> (String, Tensor) {
    let mut rng = common::Lcg(seed);
    let n = shape.iter().product();
    (name.to_string(), Tensor::f32(shape, (0..n).map(|_| rng.next_f32()).collect()))
}

/// Every output of `m` on `engine`.
pub fn outputs(engine: Engine, m: &ModelProto, inputs: &[(String, Tensor)]) -> Vec<(String, Tensor)> {
    runtime::load(engine, m, inputs, 1).unwrap().run(inputs).unwrap()
}

/// `after`'s outputs equal `before`'s (by name) within `tol` rel L2; 0 asks for bit-identical.
pub fn assert_same(before: &[(String, Tensor)], after: &[(String, Tensor)], tol: f64) {
    assert_eq!(before.len(), after.len(), "output count");
    for (name, a) in before {
        let b = &after.iter().find(|(n, _)| n == name).unwrap_or_else(|| panic!("output {name} missing")).1;
        if tol == 0.0 {
            assert!(a.bit_identical(b), "{name}: not bit-identical");
        } else {
            let e = common::rel_l2(a, b);
            assert!(e <= tol, "{name}: rel L2 {e:e} > {tol:e}");
        }
    }
}

/// A later pass (`dce`) given `rewritten` (`pass`'s output) gets the original form back under
/// its own names: the same bytes as that pass on `original`.
pub fn assert_later_passes_get_the_original(original: &ModelProto, rewritten: &ModelProto, pass: &str) {
    use prost::Message;
    let (mut plain, mut lowered) = (original.clone(), rewritten.clone());
    run_passes(&mut plain, "dce");
    run_passes(&mut lowered, "dce");
    assert!(plain.encode_to_vec() == lowered.encode_to_vec(), "dce after {pass} differs from dce alone");
}

/// `m` on ONNX Runtime and on tract gives `before` (the outputs before a rewrite, on ORT)
/// within float noise: rel L2 below 1e-6 on every output.
pub fn assert_float_noise_on_ort_and_tract(before: &[(String, Tensor)], m: &ModelProto, inputs: &[(String, Tensor)]) {
    for engine in [Engine::Ort, Engine::Tract] {
        for ((name, a), (_, b)) in before.iter().zip(outputs(engine, m, inputs)) {
            let e = crate::common::rel_l2(a, &b);
            assert!(e < 1e-6, "{name} on {engine:?}: rel L2 {e:e}");
        }
    }
}

/// Every registered pass has its test file here, with at least one test.
#[test]
fn every_pass_has_its_test_file() {
    let mut missing = Vec::new();
    for (name, file) in pdi_compile::passes::FILES {
        let stem = std::path::Path::new(file).file_stem().unwrap().to_str().unwrap();
        let test = repo().join("tests/suite/passes").join(format!("{stem}.rs"));
        match std::fs::read_to_string(&test) {
            Ok(text) if text.contains("#[test]") => {}
            _ => missing.push(format!("{name}: {}", test.display())),
        }
    }
    assert!(missing.is_empty(), "passes without a test file:\n{}", missing.join("\n"));
    assert_eq!(pdi_compile::passes::FILES.len(), pdi_compile::passes::KNOWN.len());
}

/// A pass answers to the name its registry line gives it (the runner names its warnings and
/// reports by `Pass::name`, recipes by the registry).
#[test]
fn every_pass_is_named_as_registered() {
    for name in pdi_compile::passes::KNOWN {
        let built = pdi_compile::passes::build(name, &yaml_serde::Value::Null).unwrap();
        assert_eq!(built.pass.name(), *name);
    }
}
