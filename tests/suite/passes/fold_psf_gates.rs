//! `fold-psf-gates`: with the blur map bound, every gate is a constant: a uniform gate folds
//! into its branch's last convolution (or becomes a scalar), a gate of zero removes its branch.

use crate::common::*;
use crate::compile_detect_f32::{blur_map, compile, detections, original_inputs};
use pdi_compile::runtime::Engine;
use pdi_compile::tensor::Tensor;

/// A multi-lens camera's uniform blur map makes every gate uniform: each folds into its
/// branch's last conv/BN or becomes a scalar; a gate driven to 0 removes its branch.
#[test]
fn uniform_and_zero_gates_fold_away() {
    let dir = tempfile::tempdir().unwrap();
    let f = repo().join("models/fixtures/pdinet_v5_input_op17_nofold.onnx");
    let mut model = load(&f);
    // alpha_lam = -1 with k = 0.5 gives clip(sigmoid(-4) - 0.5) = 0: the Laplacian branch is off.
    let g = model.graph.as_mut().unwrap();
    let alpha = g.initializer.iter_mut().find(|t| t.name.ends_with("alpha")).expect("alpha initializer");
    let mut v: Vec<f32> = pdi_compile::onnx::tensor_proto::to_tensor(alpha).unwrap().as_f32().unwrap().to_vec();
    v[2] = -1.0;
    *alpha = pdi_compile::onnx::tensor_proto::from_tensor(&alpha.name.clone(), &Tensor::f32(vec![3], v));
    let edited = dir.path().join("edited.onnx");
    pdi_compile::onnx::save(&model, &edited).unwrap();
    let psf_path = repo().join("calib/uniform_6x8.npy");
    let out = dir.path().join("out");
    let report = compile(&edited, &psf_path, &out);
    let gates = report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "fold-psf-gates").unwrap()["details"]["gates"].clone();
    let actions: Vec<(String, String)> = gates.as_array().unwrap().iter().map(|g| (g["branch"].as_str().unwrap().to_string(), g["action"].as_str().unwrap().to_string())).collect();
    for (branch, action) in &actions {
        match branch.as_str() {
            "laplacian" => assert!(action.starts_with("zero everywhere: branch removed"), "{actions:?}"),
            "large" => assert!(action.contains("folded into"), "{actions:?}"),
            "small" => assert!(action.contains("scalar"), "{actions:?}"),
            other => panic!("unexpected branch {other}: {actions:?}"),
        }
    }
    let cand = load(&out.join("model.onnx"));
    let grouped_3x3 = |m: &pdi_compile::onnx::proto::ModelProto| m.graph.as_ref().unwrap().node.iter().filter(|n| n.op_type == "Conv" && n.attribute.iter().any(|a| a.name == "group" && a.i.unwrap_or(1) > 1) && n.attribute.iter().any(|a| a.name == "kernel_shape" && a.ints == [3, 3])).count();
    let (before, after) = (grouped_3x3(&model), grouped_3x3(&cand));
    assert!(after < before, "the Laplacian's depthwise 3x3 is gone: {before} grouped 3x3 convolutions before, {after} after");
    let psf = blur_map(&psf_path);
    let inputs = original_inputs(&model, &psf, 4);
    let cand_inputs: Vec<(String, Tensor)> = inputs.iter().filter(|(n, _)| n != "psf_blur").cloned().collect();
    let e = rel_l2(&detections(Engine::Ort, &model, &inputs), &detections(Engine::Ort, &cand, &cand_inputs));
    assert!(e <= 1e-5, "rel L2 {e:e}");
}
