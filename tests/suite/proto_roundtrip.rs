//! Everything a CNN model carries survives decode -> encode: every attribute kind, every
//! initializer dtype PyTorch emits in raw and typed form, opsets with custom domains,
//! model/graph/node/value metadata, doc strings, producer, IR version.

use pdi_compile::onnx::proto::*;
use pdi_compile::onnx::tensor_proto::to_tensor;
use prost::Message;

fn kv(k: &str, v: &str) -> StringStringEntryProto {
    StringStringEntryProto { key: k.into(), value: v.into() }
}

fn rich_model() -> ModelProto {
    let raw = |name: &str, dt: i32, bytes: Vec<u8>, dims: Vec<i64>| TensorProto { name: name.into(), data_type: dt, raw_data: bytes, dims, ..Default::default() };
    let inits = vec![
        raw("f32", 1, 1.5f32.to_le_bytes().repeat(4), vec![2, 2]),
        raw("f16", 10, half::f16::from_f32(0.25).to_le_bytes().repeat(3), vec![3]),
        raw("i64", 7, (-7i64).to_le_bytes().repeat(2), vec![2]),
        raw("i32", 6, 9i32.to_le_bytes().to_vec(), vec![1]),
        raw("i8", 3, vec![0x80, 0x7f], vec![2]),
        raw("u8", 2, vec![0, 255], vec![2]),
        raw("bool", 9, vec![1, 0, 1], vec![3]),
        TensorProto { name: "typed_f32".into(), data_type: 1, dims: vec![2], float_data: vec![1.0, -2.0], doc_string: "doc".into(), metadata_props: vec![kv("t", "m")], ..Default::default() },
        TensorProto { name: "typed_i64".into(), data_type: 7, dims: vec![2], int64_data: vec![i64::MIN, i64::MAX], ..Default::default() },
        TensorProto { name: "typed_f16".into(), data_type: 10, dims: vec![1], int32_data: vec![0x3c00], ..Default::default() },
        TensorProto { name: "typed_bool".into(), data_type: 9, dims: vec![2], int32_data: vec![1, 0], ..Default::default() },
    ];
    let attr = |name: &str, ty: AttributeType| AttributeProto { name: name.into(), r#type: ty as i32, ..Default::default() };
    let attrs = vec![
        AttributeProto { f: Some(0.0), ..attr("f", AttributeType::Float) },
        AttributeProto { i: Some(0), ..attr("i", AttributeType::Int) },
        AttributeProto { s: Some(b"half_pixel".to_vec()), ..attr("s", AttributeType::String) },
        AttributeProto { t: Some(inits[0].clone()), ..attr("t", AttributeType::Tensor) },
        AttributeProto { g: Some(GraphProto { name: "sub".into(), ..Default::default() }), ..attr("g", AttributeType::Graph) },
        AttributeProto { floats: vec![0.5, 2.0], ..attr("floats", AttributeType::Floats) },
        AttributeProto { ints: vec![1, -1, 0], ..attr("ints", AttributeType::Ints) },
        AttributeProto { strings: vec![b"a".to_vec(), b"".to_vec()], ..attr("strings", AttributeType::Strings) },
        AttributeProto { tensors: vec![inits[2].clone()], ..attr("tensors", AttributeType::Tensors) },
        AttributeProto { graphs: vec![GraphProto::default()], ..attr("graphs", AttributeType::Graphs) },
        AttributeProto { tp: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: None })), denotation: String::new() }), ..attr("tp", AttributeType::TypeProto) },
        AttributeProto { ref_attr_name: "outer".into(), doc_string: "ref".into(), ..attr("r", AttributeType::Int) },
    ];
    let dim = |v: DimensionValue| Dimension { value: Some(v), denotation: "DATA_BATCH".into() };
    let vi = ValueInfoProto {
        name: "x".into(),
        doc_string: "input".into(),
        metadata_props: vec![kv("vi", "1")],
        r#type: Some(TypeProto {
            value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: Some(TensorShapeProto { dim: vec![dim(DimensionValue::DimParam("N".into())), dim(DimensionValue::DimValue(3))] }) })),
            denotation: "TENSOR".into(),
        }),
    };
    ModelProto {
        ir_version: 10,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }, OperatorSetIdProto { domain: "com.pdi".into(), version: 1 }],
        producer_name: "pytorch".into(),
        producer_version: "2.15.0".into(),
        domain: "ai.pdi".into(),
        model_version: 3,
        doc_string: "model doc".into(),
        metadata_props: vec![kv("names", "{0: 'People'}")],
        graph: Some(GraphProto {
            name: "main".into(),
            doc_string: "graph doc".into(),
            node: vec![NodeProto {
                name: "n0".into(),
                op_type: "Custom".into(),
                domain: "com.pdi".into(),
                input: vec!["x".into(), String::new()],
                output: vec!["y".into()],
                attribute: attrs,
                doc_string: "node doc".into(),
                metadata_props: vec![kv("source", "bridge.py:42")],
                ..Default::default()
            }],
            initializer: inits,
            input: vec![vi.clone()],
            output: vec![ValueInfoProto { name: "y".into(), ..vi.clone() }],
            value_info: vec![vi],
            quantization_annotation: vec![TensorAnnotation { tensor_name: "y".into(), quant_parameter_tensor_names: vec![kv("SCALE_TENSOR", "s")] }],
            metadata_props: vec![kv("g", "1")],
            ..Default::default()
        }),
        functions: vec![FunctionProto { name: "f".into(), domain: "com.pdi".into(), input: vec!["a".into()], output: vec!["b".into()], ..Default::default() }],
        ..Default::default()
    }
}

#[test]
fn everything_survives_a_round_trip() {
    let m = rich_model();
    let bytes = m.encode_to_vec();
    let back = ModelProto::decode(&*bytes).unwrap();
    assert_eq!(back, m);
    assert_eq!(back.encode_to_vec(), bytes, "re-encoding is byte-identical");
    let node = &back.graph.as_ref().unwrap().node[0];
    assert_eq!(node.metadata_props[0].value, "bridge.py:42");
    assert_eq!(node.attribute[1].i, Some(0), "explicit zero keeps its presence");
}

#[test]
fn every_initializer_dtype_decodes() {
    let m = rich_model();
    for t in &m.graph.as_ref().unwrap().initializer {
        let v = to_tensor(t).unwrap_or_else(|e| panic!("{}: {e:#}", t.name));
        assert_eq!(v.len() as i64, t.dims.iter().product::<i64>(), "{}", t.name);
    }
}
