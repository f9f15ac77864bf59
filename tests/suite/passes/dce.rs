//! `dce`: nodes no output needs, initializers nobody reads and stale value_info go; graph
//! inputs stay (they are the interface). The outputs are the same bits.

use super::*;

#[test]
fn what_no_output_needs_goes_and_the_interface_stays() {
    let mut m = model(
        vec![
            node("Mul", &["x", "k"], "a", vec![]),
            node("Relu", &["a"], "y", vec![]),
            node("Add", &["a", "unused_w"], "dead", vec![]),
            node("Neg", &["dead"], "dead2", vec![]),
            node("Neg", &["z"], "only_from_z", vec![]),
        ],
        vec![vi("x", &[1, 4]), vi("z", &[1, 4])],
        vec![vi("y", &[1, 4])],
        vec![init("k", vec![1], vec![2.0]), init("unused_w", vec![1, 4], vec![1.0; 4]), init("orphan", vec![2], vec![0.0; 2])],
    );
    m.graph.as_mut().unwrap().value_info = vec![vi("a", &[1, 4]), vi("dead", &[1, 4])];
    let inputs = vec![input("x", vec![1, 4], 3), input("z", vec![1, 4], 4)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let r = run_passes(&mut m, "dce");
    let d = &r[0].details;
    assert_eq!((d["nodes_removed"].as_u64(), d["initializers_removed"].as_u64(), d["value_info_removed"].as_u64()), (Some(3), Some(2), Some(1)), "{d}");
    assert_eq!(ops(&m), ["Mul", "Relu"]);
    let g = m.graph.as_ref().unwrap();
    assert_eq!(g.input.len(), 2, "a graph input is never removed");
    assert_same(&before, &outputs(Engine::Ort, &m, &inputs), 0.0);
}
