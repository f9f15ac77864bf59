//! `drop-classes`: on the committed trained models, keeping some classes is exact: the kept
//! classes' detections are the full model's.

use crate::common::*;
use crate::scene::{compile, frames, pass, verify, write, MODELS};

#[test]
fn dropping_classes_is_exact() {
    let dir = tempfile::tempdir().unwrap();
    let data = frames(dir.path());
    let scene = write(dir.path(), "classes.yaml", "classes: [Car, People]\n");
    for m in MODELS {
        let model = repo().join("models/trained").join(m);
        let full = dir.path().join(format!("{m}.full"));
        let cut = dir.path().join(format!("{m}.cut"));
        compile(&model, "passes/detect-f32.yaml", None, &full);
        let report = compile(&model, "passes/detect-f32.yaml", Some(&scene), &cut);
        let p = pass(&report, "drop-classes");
        assert_eq!(p["details"]["kept"], serde_json::json!(["Car", "People"]));
        let (before, after) = (&p["before"], &p["after"]);
        assert!(after["macs"].as_u64() < before["macs"].as_u64() && after["params"].as_u64() < before["params"].as_u64(), "{m}: {p}");
        // Against the lossless compile: the same rows of the same convolutions.
        let j = verify(&full.join("model.onnx"), &cut.join("model.onnx"), &data);
        for g in j["outputs"][0]["groups"].as_array().unwrap() {
            assert_eq!(g["ort"]["max_abs"].as_f64(), Some(0.0), "{m}: group {} differs", g["group"]);
        }
        assert_eq!(j["detection"]["identical"], true, "{m}: detections differ");
        assert!(j["detection"]["truth_boxes"].as_u64().unwrap() > 20, "{m}: too few Car/People detections to compare");
        // Against the original export (BatchNorm unfolded): float rounding only.
        let j = verify(&model, &cut.join("model.onnx"), &data);
        for g in j["outputs"][0]["groups"].as_array().unwrap() {
            assert!(g["ort"]["rel_l2"].as_f64().unwrap() <= 1e-6, "{m}: group {} rel L2 {}", g["group"], g["ort"]["rel_l2"]);
        }
        println!("{m}: drop-classes MACs {} -> {}, params {} -> {}", before["macs"], after["macs"], before["params"], after["params"]);
    }
}
