//! `promote-constants`: weights held in Constant nodes (Paddle, tf2onnx) become initializers;
//! a Constant that is a graph output stays a node. The outputs are the same bits.

use super::*;

#[test]
fn constant_weights_become_initializers_and_compute_the_same() {
    let w = Tensor::f32(vec![2, 2, 1, 1], vec![1.0, -2.0, 0.5, 3.0]);
    let mut m = model(
        vec![
            node("Constant", &[], "w", vec![tensor_attr("value", &w)]),
            node("Constant", &[], "k", vec![tensor_attr("value", &Tensor::f32(vec![1], vec![2.0]))]),
            node("Conv", &["x", "w"], "c", vec![]),
            node("Mul", &["c", "k"], "y", vec![]),
        ],
        vec![vi("x", &[1, 2, 3, 3])],
        vec![vi("y", &[1, 2, 3, 3]), vi("k", &[1])],
        vec![],
    );
    let inputs = vec![input("x", vec![1, 2, 3, 3], 1)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let r = run_passes(&mut m, "promote-constants");
    assert_eq!(r[0].details["constants_promoted"], 1, "{}", r[0].details);
    // `w` is an initializer now; `k` is a graph output, so its Constant stays.
    assert_eq!(ops(&m), ["Constant", "Conv", "Mul"]);
    assert!(m.graph.as_ref().unwrap().initializer.iter().any(|t| t.name == "w"));
    assert_same(&before, &outputs(Engine::Ort, &m, &inputs), 0.0);
}
