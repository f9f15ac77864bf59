//! The committed trained tiny PDI-Net: it detects, its card's numbers reproduce, and the
//! lossless compile keeps its accuracy. The held-out set is regenerated from its recipe
//! (models/trained/MODEL_CARD.md) by the Rust physics pipeline.

use crate::common::*;

/// Compiles `model` with `recipe` into `out`, then verifies it against `model` on `data`:
/// the compile report and the verify report.
fn compile_and_verify(model: &std::path::Path, recipe: &str, out: &std::path::Path, data: &std::path::Path) -> (serde_json::Value, serde_json::Value) {
    let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", recipe, "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let r = cli(&["verify", "--reference", model.to_str().unwrap(), "--candidate", out.join("model.onnx").to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "--data", data.to_str().unwrap(), "--runs", "1", "--no-tract", "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    (report, serde_json::from_str(&r.stdout).unwrap())
}

#[test]
fn trained_model_detects_and_survives_the_lossless_compile() {
    let model = repo().join("models/trained/pdinet_v5_tiny_trained.onnx");
    assert!(model.is_file(), "the trained model is committed");
    let card: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(repo().join("models/trained/card.json")).unwrap()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    let (_, j) = compile_and_verify(&model, "passes/detect-f32.yaml", &dir.path().join("compiled"), &data);
    let reference = &j["detection"]["reference_vs_labels"];
    let candidate = &j["detection"]["candidate_vs_labels"];
    let (m50, m5095) = (reference["map50"].as_f64().unwrap(), reference["map50_95"].as_f64().unwrap());
    println!("trained model on the held-out set: mAP@0.5 {m50:.4}, mAP@0.5:0.95 {m5095:.4}; compiled {:.4} / {:.4}", candidate["map50"], candidate["map50_95"]);
    assert!(m50 >= 0.5, "the model learned: mAP@0.5 {m50}");
    // The card's numbers (pycocotools, models/pdinet/evaluate.py) reproduce in Rust.
    // To the card's last digit (4 decimals).
    assert!((m50 - card["map50"].as_f64().unwrap()).abs() <= 5e-5, "card mAP@0.5 {} vs {m50}", card["map50"]);
    assert!((m5095 - card["map50_95"].as_f64().unwrap()).abs() <= 5e-5, "card mAP@0.5:0.95 {} vs {m5095}", card["map50_95"]);
    assert!((candidate["map50_95"].as_f64().unwrap() - m5095).abs() <= 5e-5, "lossless compile keeps accuracy");
}

/// Pruning the trained model: mAP against labels unpruned, pruned without compensation and
/// pruned with compensation, printed side by side (the closing note quotes them), and the
/// pass's own held-out comparison of the two.
#[test]
fn pruning_the_trained_model_reports_what_compensation_recovers() {
    let model = repo().join("models/trained/pdinet_v5_tiny_trained.onnx");
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    let mut rows = Vec::new();
    for mode in ["none", "lstsq"] {
        let recipe = dir.path().join(format!("{mode}.yaml"));
        let text = recipe_edit("passes/detect-pruned-f32-norecover.yaml", "compensate: lstsq,", &format!("compensate: {mode},"));
        std::fs::write(&recipe, text).unwrap();
        let (report, j) = compile_and_verify(&model, recipe.to_str().unwrap(), &dir.path().join(mode), &data);
        let prune = report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "prune").unwrap()["details"].clone();
        let d = &j["detection"];
        rows.push((mode, d["reference_vs_labels"]["map50_95"].as_f64().unwrap(), d["candidate_vs_labels"]["map50_95"].as_f64().unwrap(), d["agreement"]["map50_95"].as_f64().unwrap(), prune));
    }
    for (mode, reference, candidate, agreement, prune) in &rows {
        println!("compensate {mode}: mAP@.5:.95 unpruned {reference:.4}, pruned {candidate:.4}, agreement {agreement:.4}; held-out rel L2 {}; MACs x{:.3}", prune["output_rel_l2"], prune["macs_ratio"].as_f64().unwrap());
    }
    let lstsq = &rows[1].4["output_rel_l2"];
    let (before, after) = (lstsq["uncompensated"]["detections"].as_f64(), lstsq["compensated"]["detections"].as_f64());
    let (Some(before), Some(after)) = (before, after) else { panic!("the report compares both: {lstsq}") };
    // What compensation recovers: less held-out error than pruning without it (it is kept
    // only where it lowers that error, so equal would mean it was dropped).
    assert!(after < before, "compensation did not reduce the held-out error: {after} against {before}");
    assert!(rows[1].4["compensation"]["work"]["bias_corrected"].as_u64().unwrap() > 0);
}

/// INT8 and FP16 compiles of the trained model against labels: INT8 within 0.01 mAP@0.5:0.95
/// of the float compile, FP16 within 0.002 (the figures the closing note quotes).
#[test]
fn int8_and_fp16_keep_the_trained_models_accuracy() {
    let model = repo().join("models/trained/pdinet_v5_tiny_trained.onnx");
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    let mut maps = Vec::new();
    for recipe in ["detect-f32", "detect-int8", "detect-fp16"] {
        let (_, j) = compile_and_verify(&model, &format!("passes/{recipe}.yaml"), &dir.path().join(recipe), &data);
        let d = &j["detection"];
        let m = d["candidate_vs_labels"]["map50_95"].as_f64().unwrap();
        println!("{recipe}: mAP@.5:.95 vs labels {m:.4}, agreement with the original {:.4}", d["agreement"]["map50_95"].as_f64().unwrap());
        maps.push(m);
    }
    assert!((maps[1] - maps[0]).abs() <= 0.01, "INT8 {} vs f32 {}", maps[1], maps[0]);
    assert!((maps[2] - maps[0]).abs() <= 0.002, "FP16 {} vs f32 {}", maps[2], maps[0]);
}

/// The width-0.25 models (v5 and v8 heads): each reproduces its card's mAP to its last digit
/// through `pdi-compile verify` (the card is scored at verify's NMS IoU for its head), survives
/// the lossless compile, and clears the tiny model's mAP@0.5:0.95.
#[test]
fn width_quarter_models_reproduce_their_cards() {
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    for head in ["v5", "v8"] {
        let model = repo().join(format!("models/trained/pdinet_{head}_w0.25_trained.onnx"));
        let card: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(repo().join(format!("models/trained/pdinet_{head}_w0.25.card.json"))).unwrap()).unwrap();
        assert!(std::fs::metadata(&model).unwrap().len() <= 8 << 20, "{head}: committed models stay under 8 MB");
        let (_, j) = compile_and_verify(&model, "passes/detect-f32.yaml", &dir.path().join(head), &data);
        let (reference, candidate) = (&j["detection"]["reference_vs_labels"], &j["detection"]["candidate_vs_labels"]);
        let (m50, m5095) = (reference["map50"].as_f64().unwrap(), reference["map50_95"].as_f64().unwrap());
        println!("{head} width 0.25: mAP@0.5 {m50:.4}, mAP@0.5:0.95 {m5095:.4} (card {} / {})", card["map50"], card["map50_95"]);
        assert!((m50 - card["map50"].as_f64().unwrap()).abs() <= 5e-5, "{head}: card mAP@0.5 {} vs {m50}", card["map50"]);
        assert!((m5095 - card["map50_95"].as_f64().unwrap()).abs() <= 5e-5, "{head}: card mAP@0.5:0.95 {} vs {m5095}", card["map50_95"]);
        assert!(m5095 >= 0.453, "{head}: at least the tiny model's mAP@0.5:0.95");
        assert!((candidate["map50_95"].as_f64().unwrap() - m5095).abs() <= 5e-5, "{head}: lossless compile keeps accuracy");
    }
}

/// The width-0.25 models fine-tuned at the camera's 640x480 (models/finetune-640.sh): each
/// takes 640x480 frames, stays small enough for a clone, and reproduces its card to the last
/// digit through `pdi-compile verify` on the held-out scenes kept at 640x480. One test per
/// head: the two run side by side, and the suite does not end on one of them alone.
fn camera_resolution_model_reproduces_its_card(head: &str) {
    let data = eval_frames_at(200, "640x480");
    let model = repo().join(format!("models/trained/pdinet_{head}_w0.25_640x480_trained.onnx"));
    let card: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(repo().join(format!("models/trained/pdinet_{head}_w0.25_640x480.card.json"))).unwrap()).unwrap();
    assert!(std::fs::metadata(&model).unwrap().len() <= 8 << 20, "{head}: committed models stay under 8 MB");
    let m = load(&model);
    let dims = pdi_compile::ir::shapes::declared(&m.graph.as_ref().unwrap().input[0]).shape.unwrap();
    assert_eq!(dims, [1, 1, 480, 640], "{head}: a 640x480 model");
    // The model against itself: verify runs it once per frame and scores it against labels.
    let path = model.to_str().unwrap();
    let r = cli(&["verify", "--reference", path, "--candidate", path, "--psf", "calib/single_lwir_blur.npy", "--data", data.to_str().unwrap(), "--runs", "0", "--no-tract", "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert_eq!(j["candidate_is_reference"], true, "{head}: the model ran twice per frame");
    let labels = &j["detection"]["reference_vs_labels"];
    let (m50, m5095) = (labels["map50"].as_f64().unwrap(), labels["map50_95"].as_f64().unwrap());
    println!("{head} at 640x480: mAP@0.5 {m50:.4}, mAP@0.5:0.95 {m5095:.4} (card {} / {})", card["map50"], card["map50_95"]);
    assert!((m50 - card["map50"].as_f64().unwrap()).abs() <= 5e-5, "{head}: card mAP@0.5 {} vs {m50}", card["map50"]);
    assert!((m5095 - card["map50_95"].as_f64().unwrap()).abs() <= 5e-5, "{head}: card mAP@0.5:0.95 {} vs {m5095}", card["map50_95"]);
}

#[test]
fn camera_resolution_v5_reproduces_its_card() {
    camera_resolution_model_reproduces_its_card("v5");
}

#[test]
fn camera_resolution_v8_reproduces_its_card() {
    camera_resolution_model_reproduces_its_card("v8");
}
