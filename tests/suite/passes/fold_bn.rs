//! `fold-bn`: a BatchNormalization after a convolution folds into its weights and bias when
//! its variance plus epsilon keeps the scale finite; otherwise it stays, named.

use super::*;

/// x -> Conv(2->2, 1x1) -> BN(var = [0, 1e-30], eps) -> Identity -> y, plus a duplicate initializer.
pub fn conv_bn(eps: f32) -> ModelProto {
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

pub fn output(model: &ModelProto) -> Tensor {
    let x = Tensor::f32(vec![1, 2, 3, 3], (0..18).map(|i| i as f32 * 0.1 - 0.7).collect());
    let inputs = vec![("x".to_string(), x)];
    runtime::load(Engine::Ort, model, &inputs, 1).unwrap().run(&inputs).unwrap().remove(0).1
}

#[test]
fn bn_with_tiny_variance_folds_when_eps_keeps_it_finite() {
    let mut m = conv_bn(1e-5);
    let before = output(&m);
    let reports = run_passes(&mut m, "fold-bn, cleanup, dce");
    assert_eq!(reports[0].details["folded_into_conv"], 1, "{}", reports[0].details);
    let ops: Vec<&str> = m.graph.as_ref().unwrap().node.iter().map(|n| n.op_type.as_str()).collect();
    assert_eq!(ops, ["Conv", "Add"], "BN folded, Identity bypassed");
    let e = crate::common::rel_l2(&before, &output(&m));
    assert!(e < 1e-6, "rel L2 {e:e}");
}

#[test]
fn bn_with_zero_variance_and_eps_is_left_and_named() {
    let mut m = conv_bn(0.0);
    let reports = run_passes(&mut m, "fold-bn");
    let left = reports[0].details["left"].as_array().unwrap();
    assert_eq!(left.len(), 1);
    assert!(left[0]["reason"].as_str().unwrap().contains("infinite"), "{}", left[0]);
    assert!(m.graph.as_ref().unwrap().node.iter().any(|n| n.op_type == "BatchNormalization"));
}
