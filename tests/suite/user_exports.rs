//! Models exported the way users export them (`models/fixtures/exports/`, made by
//! `models/pdinet/export.py` with the seed of the standard fixture, so the weights match
//! `pdinet_v5_input_op17_nofold.onnx`): detection output only, a three-channel image input,
//! weights in Constant nodes. Each must inspect right, compile losslessly with the shipped
//! recipe and no flags, and quantize on single-channel calibration frames.

use crate::common::*;
use std::path::PathBuf;

const STANDARD: &str = "models/fixtures/pdinet_v5_input_op17_nofold.onnx";

fn export(name: &str) -> PathBuf {
    let p = repo().join("models/fixtures/exports").join(format!("pdinet_v5_input_op17_nofold_{name}.onnx"));
    assert!(p.exists(), "fixture {} is committed", p.display());
    p
}

fn inspect(path: &std::path::Path) -> serde_json::Value {
    let r = cli(&["inspect", path.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

#[test]
fn inspect_reads_every_export() {
    let standard = inspect(&repo().join(STANDARD));
    let det_params = standard["params"]["detection_only"].as_u64().unwrap() + standard["params"]["shared"].as_u64().unwrap();

    let detonly = inspect(&export("detonly"));
    let roles: Vec<&str> = detonly["outputs"].as_array().unwrap().iter().map(|o| o["role"].as_str().unwrap()).collect();
    assert_eq!(roles, ["detection"], "{detonly}");
    // The same detection weights, nothing for the decoder that was never exported. Not to the
    // element: the exporter deduplicates equal initializers (fresh BatchNorm ones and zeros)
    // differently when the decoder is not there to share them.
    let total = detonly["params"]["total"].as_u64().unwrap();
    assert!(total.abs_diff(det_params) * 100 <= det_params, "{total} parameters against {det_params}: {}", detonly["params"]);
    assert_eq!(detonly["params"]["reconstruction_only"], 0);

    let rgb = inspect(&export("3ch"));
    assert_eq!(rgb["inputs"][0]["shape"], serde_json::json!([1, 3, 192, 256]));
    let roles: Vec<&str> = rgb["outputs"].as_array().unwrap().iter().map(|o| o["role"].as_str().unwrap()).collect();
    assert_eq!(roles, ["reconstruction", "detection"], "{}", rgb["outputs"]);

    let constw = inspect(&export("constw"));
    assert!(constw["ops"]["Constant"].as_u64().unwrap() > 50, "weights are in Constant nodes: {}", constw["ops"]);
    assert_eq!(constw["params"], standard["params"], "Constant-node weights count as parameters");
    assert_eq!(constw["macs"], standard["macs"]);
}

/// The lossless compile with the shipped recipe and no flags: rel L2 ≤ 1e-5 against the export.
#[test]
fn detect_f32_is_lossless_on_every_export() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["detonly", "3ch", "constw"] {
        let model = export(name);
        let out = dir.path().join(name);
        let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap(), "--json"]);
        assert_eq!(r.code, 0, "{name}: {}", r.stderr);
        let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
        if name == "detonly" {
            assert!(r.stderr.contains("keeping every output"), "strip-recon says it kept everything: {}", r.stderr);
        }
        if name == "constw" {
            let promoted = report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "promote-constants").unwrap();
            assert!(promoted["details"]["constants_promoted"].as_u64().unwrap() > 50, "{promoted}");
            assert!(report["after"]["params"].as_u64().unwrap() > 0, "{}", report["after"]);
        }
        let v = cli(&["verify", "--reference", model.to_str().unwrap(), "--candidate", out.join("model.onnx").to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "--random", "3", "--runs", "0", "--no-tract", "--json"]);
        assert_eq!(v.code, 0, "{name}: {}", v.stderr);
        let v: serde_json::Value = serde_json::from_str(&v.stdout).unwrap();
        for o in v["outputs"].as_array().unwrap() {
            let e = o["ort"]["rel_l2"].as_f64().unwrap();
            assert!(e <= 1e-5, "{name}: output {} rel L2 {e}", o["name"]);
        }
    }
}

/// INT8 calibrates every export on the physics pipeline's single-channel frames.
#[test]
fn detect_int8_runs_on_every_export() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("int8.yaml");
    // The exports' random weights leave INT8 objectness near cosine 0.8 against float: this
    // test is about calibrating every export, so the hard limit (tests/quantize.rs) is lifted.
    std::fs::write(&recipe, recipe_edit("passes/detect-int8.yaml", "calib_frames: 64", "calib_frames: 6, analysis_frames: 2, held_out_frames: 2, hard_limit: {max_rel_l2: 1.0e9, min_cosine: -1}")).unwrap();
    for name in ["detonly", "3ch", "constw"] {
        let model = export(name);
        let out = dir.path().join(name);
        let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 0, "{name}: {}", r.stderr);
        let ops = &inspect(&out.join("model.onnx"))["ops"];
        assert!(ops["QuantizeLinear"].as_u64().unwrap_or(0) > 10, "{name}: quantized: {ops}");
        assert_eq!(r.stderr.contains("replicated"), name == "3ch", "{name}: {}", r.stderr);
    }
}

/// A trained detector that is not PDI-Net (a YOLO on the raw frame: no reconstruction, no
/// PALS-Bridge) gets the lossless passes and INT8; the physics passes say in one line why they
/// did nothing, and a blur map given for it is refused in one line.
#[test]
fn a_detector_that_is_not_pdinet_gets_the_lossless_passes_and_int8() {
    let model = repo().join("models/fixtures/exports/plain_v5_op17.onnx");
    let info = inspect(&model);
    assert_eq!(info["head"]["kind"], "yolov5-anchor", "{}", info["head"]);
    assert!(info["bridge"]["gates"].as_array().unwrap().is_empty() && info["bridge"]["blur_maps"].as_array().unwrap().is_empty());

    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f32");
    let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let details = |pass: &str| report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == pass).unwrap()["details"].clone();
    assert!(details("bind-psf")["reason"].as_str().unwrap().contains("no PALS-Bridge"), "{}", details("bind-psf"));
    assert!(details("fold-psf-gates")["note"].as_str().unwrap().contains("no PALS-Bridge"), "{}", details("fold-psf-gates"));
    let v = cli(&["verify", "--reference", model.to_str().unwrap(), "--candidate", out.join("model.onnx").to_str().unwrap(), "--random", "3", "--runs", "0", "--json"]);
    assert_eq!(v.code, 0, "{}", v.stderr);
    let v: serde_json::Value = serde_json::from_str(&v.stdout).unwrap();
    assert!(v["outputs"][0]["ort"]["rel_l2"].as_f64().unwrap() <= 1e-5, "{}", v["outputs"][0]);

    let with_psf = cli(&["compile", model.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", "calib/single_lwir_blur.npy", "-o", dir.path().join("psf").to_str().unwrap()]);
    assert_eq!(with_psf.code, 2, "{}", with_psf.stderr);
    let errors: Vec<&str> = with_psf.stderr.lines().filter(|l| l.starts_with("error:")).collect();
    assert!(errors.len() == 1 && errors[0].contains("no PALS-Bridge") && errors[0].contains("without --psf"), "{}", with_psf.stderr);

    let recipe = dir.path().join("int8.yaml");
    std::fs::write(&recipe, recipe_edit("passes/detect-int8.yaml", "calib_frames: 64", "calib_frames: 6, analysis_frames: 2, held_out_frames: 2")).unwrap();
    let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", recipe.to_str().unwrap(), "-o", dir.path().join("int8").to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(inspect(&dir.path().join("int8/model.onnx"))["ops"]["QuantizeLinear"].as_u64().unwrap_or(0) > 10);
}
