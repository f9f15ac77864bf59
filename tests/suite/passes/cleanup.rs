//! `cleanup`: duplicate initializers merge, Identity nodes are bypassed; outputs bit-identical.

use super::fold_bn::{conv_bn, output};
use super::*;
use pdi_compile::onnx::tensor_proto::to_tensor;

#[test]
fn cleanup_merges_duplicate_initializers() {
    let mut m = conv_bn(1e-5);
    m.graph.as_mut().unwrap().node[3].input[1] = "dup".into();
    m.graph.as_mut().unwrap().node.push(node("Mul", &["y", "beta_copy"], "z", vec![]));
    m.graph.as_mut().unwrap().output = vec![vi("z", &[1, 2, 3, 3])];
    let before = output(&m);
    let reports = run_passes(&mut m, "cleanup");
    assert_eq!(reports[0].details["initializers_merged"], 1, "{}", reports[0].details);
    assert!(before.bit_identical(&output(&m)));
    let names: Vec<&str> = m.graph.as_ref().unwrap().initializer.iter().map(|t| t.name.as_str()).collect();
    assert!(!(names.contains(&"dup") && names.contains(&"beta_copy")), "{names:?}");
    let _ = to_tensor(&m.graph.as_ref().unwrap().initializer[0]).unwrap();
}
