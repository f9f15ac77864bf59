//! `fold-constants`: whatever is computable at compile time is computed once, by ONNX Runtime
//! itself, so the folded model gives the same bits.

use super::*;
use crate::compile_detect_f32::fold_constants_is_bit_exact_on;

/// PyTorch's reshape chain (Shape -> Gather -> Unsqueeze -> Concat -> Reshape) and arithmetic
/// on initializers fold away; what reads the graph input stays.
#[test]
fn shape_chains_and_constant_arithmetic_fold_away() {
    use pdi_compile::tensor::TensorData;
    let i64s = |name: &str, v: Vec<i64>| from_tensor(name, &Tensor::new(vec![v.len()], TensorData::I64(v)));
    let mut m = model(
        vec![
            node("Shape", &["x"], "s", vec![]),
            node("Gather", &["s", "zero"], "n", vec![pdi_compile::onnx::attr::make_int("axis", 0)]),
            node("Unsqueeze", &["n", "axes"], "n1", vec![]),
            node("Concat", &["n1", "minus_one"], "shape", vec![pdi_compile::onnx::attr::make_int("axis", 0)]),
            node("Reshape", &["x", "shape"], "flat", vec![]),
            node("Mul", &["a", "b"], "ab", vec![]),
            node("Add", &["flat", "ab"], "y", vec![]),
        ],
        vec![vi("x", &[2, 3, 4])],
        vec![vi("y", &[2, 12])],
        vec![
            from_tensor("zero", &Tensor::new(vec![], TensorData::I64(vec![0]))),
            i64s("axes", vec![0]),
            i64s("minus_one", vec![-1]),
            init("a", vec![12], (0..12).map(|i| i as f32).collect()),
            init("b", vec![12], vec![0.5; 12]),
        ],
    );
    let inputs = vec![input("x", vec![2, 3, 4], 7)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let r = run_passes(&mut m, "fold-constants, dce");
    assert!(r[0].details["nodes_folded"].as_u64().unwrap() >= 5, "{}", r[0].details);
    assert_eq!(ops(&m), ["Reshape", "Add"]);
    assert_same(&before, &outputs(Engine::Ort, &m, &inputs), 0.0);
}

/// On two fixtures (v5 with the map as an input, v8 with it baked, neither folded by the
/// exporter): up to fold-constants the compile is bit-identical.
#[test]
fn fixtures_fold_bit_exact() {
    fold_constants_is_bit_exact_on(&["pdinet_v5_input_op13_nofold.onnx", "pdinet_v8_const_op17_nofold.onnx"]);
}
