//! The lossless pipeline (passes/detect-f32.yaml) on every fixture variant: detections equal
//! the original's on ORT, nothing constant is left to compute, tract agrees.

use crate::common::*;
use pdi_compile::ir::Graph;
use pdi_compile::onnx::proto::ModelProto;
use pdi_compile::optics::npy;
use pdi_compile::runtime::{self, Engine};
use pdi_compile::tensor::Tensor;
use std::path::Path;

pub(crate) fn blur_map(path: &Path) -> Tensor {
    let a = npy::read(path).unwrap();
    Tensor::f32(vec![1, 1, 6, 8], a.data)
}

/// Inputs for the original: the image, plus the blur map where it is an input.
pub(crate) fn original_inputs(model: &ModelProto, psf: &Tensor, seed: u64) -> Vec<(String, Tensor)> {
    inputs_for(model, seed).into_iter().map(|(n, t)| if n == "psf_blur" { (n, psf.clone()) } else { (n, t) }).collect()
}

pub(crate) fn compile(model: &Path, psf: &Path, out: &Path) -> serde_json::Value {
    let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", psf.to_str().unwrap(), "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}: {}", model.display(), r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

pub(crate) fn detections(engine: Engine, model: &ModelProto, inputs: &[(String, Tensor)]) -> Tensor {
    let out = runtime::load(engine, model, inputs, 1).unwrap().run(inputs).unwrap();
    out.into_iter().find(|(n, _)| n == "detections").expect("detections output").1
}

fn assert_nothing_constant_left(model: &ModelProto, name: &str) {
    let g = model.graph.as_ref().unwrap();
    Graph::build(g).unwrap();
    let consts: std::collections::HashSet<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
    for n in &g.node {
        assert!(!matches!(n.op_type.as_str(), "Shape" | "Gather" | "Resize" | "Constant" | "ConstantOfShape" | "BatchNormalization" | "Identity"), "{name}: {} left", n.op_type);
        let all_const = n.input.iter().filter(|i| !i.is_empty()).all(|i| consts.contains(i.as_str()));
        assert!(!all_const, "{name}: {} '{}' computes only constants", n.op_type, n.name);
    }
    assert_eq!(g.output.len(), 1, "{name}: only the detection output remains");
}

#[test]
fn detect_f32_is_lossless_on_every_fixture() {
    let dir = tempfile::tempdir().unwrap();
    let psf_path = repo().join("calib/radial_6x8.npy");
    let psf = blur_map(&psf_path);
    for f in fixtures() {
        let name = f.file_name().unwrap().to_str().unwrap().to_string();
        let out = dir.path().join(&name);
        let report = compile(&f, &psf_path, &out);
        let gates = report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "fold-psf-gates").unwrap()["details"]["gates"].as_array().unwrap().len();
        assert_eq!(gates, 3, "{name}: gates found by fold-psf-gates");
        let (orig, cand) = (load(&f), load(&out.join("model.onnx")));
        assert_nothing_constant_left(&cand, &name);
        assert!(cand.graph.as_ref().unwrap().input.iter().all(|i| i.name != "psf_blur"), "{name}: blur map still an input");
        let inputs = original_inputs(&orig, &psf, 21);
        let cand_inputs: Vec<(String, Tensor)> = inputs.iter().filter(|(n, _)| n != "psf_blur").cloned().collect();
        let reference = detections(Engine::Ort, &orig, &inputs);
        let on_ort = detections(Engine::Ort, &cand, &cand_inputs);
        let on_tract = detections(Engine::Tract, &cand, &cand_inputs);
        let (e_ort, e_tract) = (rel_l2(&reference, &on_ort), rel_l2(&on_ort, &on_tract));
        assert!(e_ort <= 1e-5, "{name}: candidate vs original on ORT rel L2 {e_ort:e}");
        assert!(e_tract <= 1e-4, "{name}: candidate on tract vs ORT rel L2 {e_tract:e}");
        let macs = (report["before"]["macs"].as_u64().unwrap(), report["after"]["macs"].as_u64().unwrap());
        assert!(macs.1 < macs.0, "{name}: MACs {macs:?}");
    }
}

#[test]
fn a_blur_map_input_without_psf_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let f = repo().join("models/fixtures/pdinet_v8_input_op13_fold.onnx");
    let r = cli(&["compile", f.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "-o", dir.path().join("o").to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("--psf"), "{}", r.stderr);
    let bad = dir.path().join("bad.yaml");
    std::fs::write(&bad, "grid: [6, 8]\nvalues: [0.5]\n").unwrap();
    let r = cli(&["compile", f.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", bad.to_str().unwrap(), "-o", dir.path().join("o").to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("needs 48 values"), "{}", r.stderr);
}

/// fold-constants evaluates with ORT itself: up to it, the compile of each fixture is
/// bit-identical (`passes::fold_constants` runs it).
pub(crate) fn fold_constants_is_bit_exact_on(fixtures: &[&str]) {
    let dir = tempfile::tempdir().unwrap();
    let pipeline = dir.path().join("fold.yaml");
    std::fs::write(&pipeline, "name: fold\npasses: [strip-recon, bind-psf, fold-constants, dce, cleanup]\n").unwrap();
    let psf_path = repo().join("calib/radial_6x8.npy");
    let psf = blur_map(&psf_path);
    for f in fixtures {
        let f = repo().join("models/fixtures").join(f);
        let out = dir.path().join("o");
        let r = cli(&["compile", f.to_str().unwrap(), "--pipeline", pipeline.to_str().unwrap(), "--psf", psf_path.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let (orig, cand) = (load(&f), load(&out.join("model.onnx")));
        assert!(cand.graph.as_ref().unwrap().node.iter().all(|n| n.op_type != "Shape" && n.op_type != "Clip"), "shape chains and gates folded");
        let inputs = original_inputs(&orig, &psf, 8);
        let cand_inputs: Vec<(String, Tensor)> = inputs.iter().filter(|(n, _)| n != "psf_blur").cloned().collect();
        assert!(detections(Engine::Ort, &orig, &inputs).bit_identical(&detections(Engine::Ort, &cand, &cand_inputs)), "{}", f.display());
    }
}
