//! `drop-strides`: removing a detection scale keeps the detections of the object sizes the
//! scene asks for.

use crate::common::*;
use crate::scene::{compile, frames, pass, verify, write, MODELS};
use serde_json::Value;

#[test]
fn dropping_strides_removes_a_scale_and_keeps_small_objects() {
    let dir = tempfile::tempdir().unwrap();
    let data = frames(dir.path());
    let scene = write(dir.path(), "size.yaml", "object_px: [0, 24]\n");
    for m in MODELS {
        let model = repo().join("models/trained").join(m);
        let out = dir.path().join(m);
        let report = compile(&model, "passes/detect-f32.yaml", Some(&scene), &out);
        let p = pass(&report, "drop-strides");
        let dropped: Vec<&Value> = p["details"]["levels"].as_array().unwrap().iter().filter(|l| l["kept"] == false).collect();
        assert!(!dropped.is_empty(), "{m}: no scale dropped: {p}");
        // The dropped scale's head convolution and the bottom-up path to it are gone.
        assert!(p["after"]["nodes"].as_u64() < p["before"]["nodes"].as_u64());
        let compiled = load(&out.join("model.onnx"));
        let names: Vec<&str> = compiled.graph.as_ref().unwrap().node.iter().map(|n| n.name.as_str()).collect();
        assert!(!names.iter().any(|n| n.contains("out5")), "{m}: the neck's stride-32 output block survived");
        let j = verify(&model, &out.join("model.onnx"), &data);
        let agreement = j["detection"]["agreement"]["map50_95"].as_f64().unwrap();
        println!("{m}: dropped strides {:?}, MACs {} -> {}, agreement on 0..24 px {agreement:.4}", dropped.iter().map(|l| &l["stride"]).collect::<Vec<_>>(), p["before"]["macs"], p["after"]["macs"]);
        assert!(agreement >= 0.99, "{m}: agreement {agreement}");
    }
}
