//! Inferred dtypes and static shapes equal what ONNX Runtime actually produces, for every
//! value of every fixture (PyTorch's Shape/Gather/Concat/Reshape chains included).

use crate::common::*;
use pdi_compile::ir::{infer, Graph};
use pdi_compile::onnx::proto::*;
use pdi_compile::runtime::{self, Engine};

#[test]
fn inferred_shapes_match_ort_on_every_value() {
    for f in fixtures() {
        let model = load(&f);
        let g = model.graph.as_ref().unwrap();
        let graph = Graph::build(g).unwrap();
        let inf = infer(&graph);
        assert!(inf.warnings.is_empty(), "{}: {:?}", f.display(), inf.warnings);
        let values: Vec<String> = g.node.iter().flat_map(|n| n.output.iter().cloned()).filter(|o| !o.is_empty()).collect();
        let exposed = pdi_compile::onnx::edit::expose_outputs(&model, &values);
        let inputs = inputs_for(&model, 5);
        let out = runtime::load(Engine::Ort, &exposed, &inputs, 1).unwrap().run(&inputs).unwrap();
        let mut checked = 0;
        for (name, t) in &out {
            let vt = inf.types.get(name).unwrap_or_else(|| panic!("{}: no type for {name}", f.display()));
            assert_eq!(vt.static_shape().as_ref(), Some(&t.shape), "{}: shape of {name}", f.display());
            assert_eq!(vt.dtype, Some(t.dtype()), "{}: dtype of {name}", f.display());
            checked += 1;
        }
        assert!(checked > 300, "{}: only {checked} values", f.display());
    }
}

#[test]
fn unknown_ops_keep_declared_shapes_and_are_named() {
    let dims = |d: &[i64]| TensorShapeProto { dim: d.iter().map(|&v| Dimension { value: Some(DimensionValue::DimValue(v)), denotation: String::new() }).collect() };
    let vi = |name: &str, d: &[i64]| ValueInfoProto {
        name: name.into(),
        r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: Some(dims(d)) })), denotation: String::new() }),
        ..Default::default()
    };
    let node = |op: &str, domain: &str, i: &str, o: &str| NodeProto { op_type: op.into(), domain: domain.into(), input: vec![i.into()], output: vec![o.into()], ..Default::default() };
    let g = GraphProto {
        node: vec![node("FancyOp", "com.vendor", "x", "y"), node("Relu", "", "y", "z")],
        input: vec![vi("x", &[1, 4])],
        value_info: vec![vi("y", &[2, 7])],
        output: vec![vi("z", &[2, 7])],
        ..Default::default()
    };
    let graph = Graph::build(&g).unwrap();
    let inf = infer(&graph);
    assert_eq!(inf.shape("y"), Some(vec![2, 7]), "declared shape kept, not guessed");
    assert_eq!(inf.shape("z"), Some(vec![2, 7]), "known ops continue from it");
    assert_eq!(inf.warnings.len(), 1);
    assert!(inf.warnings[0].contains("com.vendor:FancyOp"), "{:?}", inf.warnings);
}
