//! `pdi-compile stress` on the trained tiny model: the lossless compile agrees with the
//! export under every condition, the INT8 compile's clipping is measured per layer, the
//! output folder is complete, and gates, bad condition files and bad gates are answered
//! as a CI job needs (exit 1, exit 2 with one line).

use crate::common::*;
use std::path::Path;

const TINY: &str = "models/trained/pdinet_v5_tiny_trained.onnx";
const PSF: &str = "calib/single_lwir_blur.npy";

fn compile(recipe: &str, out: &Path, extra: &[&str]) {
    let mut args = vec!["compile", TINY, "--pipeline", recipe, "--psf", PSF, "-o", out.to_str().unwrap()];
    args.extend_from_slice(extra);
    let r = cli(&args);
    assert_eq!(r.code, 0, "{}", r.stderr);
}

/// The scale of the image input's quantizer (on the image, or on its 2x2 pixel blocks where
/// `space-to-depth` runs the first block on them: the same values).
fn image_scale(model: &Path) -> f32 {
    let m = load(model);
    let g = m.graph.unwrap();
    let blocks = g.node.iter().find(|n| n.op_type == "SpaceToDepth" && n.input[0] == "image").map(|n| n.output[0].as_str());
    let q = g.node.iter().find(|n| n.op_type == "QuantizeLinear" && (n.input[0] == "image" || Some(n.input[0].as_str()) == blocks)).expect("the image input is quantized");
    let t = g.initializer.iter().find(|t| t.name == q.input[1]).unwrap();
    pdi_compile::onnx::tensor_proto::to_tensor(t).unwrap().as_f32().unwrap()[0]
}

/// `calib_conditions` widens the ranges the stressed frames need (gain x2 saturates where
/// clean frames stop), reports the held-out error under each condition, and refuses names
/// it does not know and conditions a folded model cannot see.
#[test]
fn robust_calibration_covers_its_conditions() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // Every layer INT8: the image's range and the saturation a doubled gain causes show first
    // in the layers nearest the frame.
    let text = every_layer_int8().replace("calib_frames: 64", "calib_frames: 16, analysis_frames: 4, held_out_frames: 4");
    let with = |conditions: &str| {
        let p = d.join(format!("r{}.yaml", conditions.len()));
        std::fs::write(&p, text.replace("narrow_float: 0}", &format!("narrow_float: 0, calib_conditions: [{conditions}]}}"))).unwrap();
        p
    };
    let plain = d.join("plain.yaml");
    std::fs::write(&plain, &text).unwrap();
    compile(plain.to_str().unwrap(), &d.join("plain"), &[]);
    let robust = with("gain_x2");
    let r = cli(&["compile", TINY, "--pipeline", robust.to_str().unwrap(), "--psf", PSF, "-o", d.join("robust").to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let q = &report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "quantize").unwrap()["details"];
    assert_eq!(q["held_out_under_conditions"][0]["condition"], "gain_x2", "{q}");
    assert!(q["held_out_under_conditions"][0]["worst_output_rel_l2"].as_f64().unwrap().is_finite());
    let (a, b) = (image_scale(&d.join("plain/model.onnx")), image_scale(&d.join("robust/model.onnx")));
    assert!(b > 1.2 * a, "gain x2 frames widen the image range: scale {a} -> {b}");
    for (bad, says) in [("gain_x3", "no stress condition 'gain_x3'"), ("blur_shift_1", "changes the blur map")] {
        let r = cli(&["compile", TINY, "--pipeline", with(bad).to_str().unwrap(), "--psf", PSF, "-o", d.join("bad").to_str().unwrap()]);
        assert_eq!(r.code, 2, "{}", r.stderr);
        assert!(r.stderr.contains(says) && r.stderr.trim().lines().count() == 1, "{}", r.stderr);
    }
}

#[test]
fn stress_measures_the_compiles_under_each_condition_and_gates_them() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    compile("passes/detect-f32.yaml", &d.join("f32"), &[]);
    let int8 = d.join("int8.yaml");
    std::fs::write(&int8, every_layer_int8().replace("calib_frames: 64", "calib_frames: 16")).unwrap();
    compile(int8.to_str().unwrap(), &d.join("int8"), &[]);
    let conditions = d.join("conditions.yaml");
    std::fs::write(&conditions, "frames: 6\nconditions:\n  - {kind: clean}\n  - {kind: gain, gain: [2.0]}\n  - {kind: hot_objects, size_px: 20}\n  - {kind: blur_offset, delta: 0.1}\n  - {kind: nan_pixels, share: 0.001}\n").unwrap();
    let (f32c, int8c) = (d.join("f32/model.onnx"), d.join("int8/model.onnx"));
    let out = d.join("stress");
    let base = ["stress", "--reference", TINY, "--candidate", f32c.to_str().unwrap(), "--candidate", int8c.to_str().unwrap(), "--psf", PSF, "--conditions", conditions.to_str().unwrap()];
    let mut args = base.to_vec();
    args.extend(["-o", out.to_str().unwrap(), "--json"]);
    let r = cli(&args);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    for f in ["stress.json", "stress.md", "stress.svg", "stress.png"] {
        assert!(out.join(f).metadata().is_ok_and(|m| m.len() > 100), "{f} written");
    }
    let conds = report["conditions"].as_array().unwrap();
    assert_eq!(conds.len(), 5);
    let get = |name: &str, cand: &str| conds.iter().find(|c| c["name"] == name).unwrap()["candidates"][cand].clone();
    // The lossless compile folds the blur map: exact on the frames, moved only by the map's drift.
    for c in ["clean", "gain_x2", "hot_objects_20px"] {
        let o = get(c, "f32");
        assert!(o["worst_rel_l2"].as_f64().unwrap() < 1e-4, "{c}: {o}");
        let agreement = o["agreement"].as_f64().unwrap_or_else(|| panic!("{c}: no agreement measured (nothing detected?): {o}"));
        assert!(agreement > 0.99, "{c}: {o}");
    }
    assert!(get("blur_+0.1", "f32")["worst_rel_l2"].as_f64().unwrap() > 1e-3, "a folded map does not follow the drift");
    let clean8 = get("clean", "int8");
    assert_eq!(clean8["layers"]["measure"], "saturation", "{clean8}");
    assert!(clean8["layers"]["layers"].as_u64().unwrap() > 10);
    let sat = |c: &str| get(c, "int8")["layers"]["worst"].as_f64().unwrap();
    assert!(sat("gain_x2") > sat("clean"), "doubling the gain clips more: {} vs {}", sat("gain_x2"), sat("clean"));
    let nan = conds.iter().find(|c| c["name"] == "nan_pixels_0.1%").unwrap();
    assert!(nan["reference_nonfinite"].as_u64().unwrap() > 0, "NaN pixels reach the reference's outputs");
    assert!(std::fs::read_to_string(out.join("stress.md")).unwrap().contains("## What breaks"));

    // A gate nobody can meet fails with exit 1 and a JUnit file; a gate naming a condition
    // the run lacks, and a bad condition file, are refused with exit 2 and one line.
    let gate = d.join("gate.yaml");
    std::fs::write(&gate, "min_agreement: 1.01\nconditions: [clean]\n").unwrap();
    let junit = d.join("junit.xml");
    let gated = d.join("gated");
    let mut args = base.to_vec();
    args.extend(["-o", gated.to_str().unwrap(), "--gate", gate.to_str().unwrap(), "--junit", junit.to_str().unwrap()]);
    let r = cli(&args);
    assert_eq!(r.code, 1, "{}", r.stderr);
    assert!(std::fs::read_to_string(&junit).unwrap().contains("<failure"));
    std::fs::write(&gate, "min_agreement: 0.5\nconditions: [clear]\n").unwrap();
    let r = cli(&args);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("'clear'") && r.stderr.trim().lines().count() == 1, "{}", r.stderr);
    std::fs::write(&conditions, "conditions: [{kind: gain, gain: 0}]").unwrap();
    let bad = d.join("bad");
    let r = cli(&base.iter().copied().chain(["-o", bad.to_str().unwrap()]).collect::<Vec<_>>());
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("gain 0 is outside") && r.stderr.trim().lines().count() == 1, "{}", r.stderr);
    assert!(!d.join("bad").exists(), "nothing written for a refused run");
}
