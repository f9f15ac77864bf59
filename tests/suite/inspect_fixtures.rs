//! `inspect --json` on every fixture: the reconstruction/detection/shared split, the three
//! PALS-Bridge gates, the blur map's source and the head kind.

use crate::common::*;
use serde_json::Value;

#[test]
fn inspect_recognizes_pdinet_parts() {
    for f in fixtures() {
        let name = f.file_name().unwrap().to_str().unwrap().to_string();
        let r = cli(&["inspect", f.to_str().unwrap(), "--json"]);
        assert_eq!(r.code, 0, "{name}: {}", r.stderr);
        let j: Value = serde_json::from_str(&r.stdout).unwrap();
        let macs = &j["macs"];
        let part = |k: &str| macs[k].as_u64().unwrap();
        let total = part("total");
        assert!(part("reconstruction_only") > 0, "{name}: no reconstruction-only MACs");
        assert!(part("detection_only") > 0 && part("shared") > 0, "{name}: {macs}");
        let sum = part("reconstruction_only") + part("detection_only") + part("shared");
        assert!((sum as f64 - total as f64).abs() <= 0.01 * total as f64, "{name}: parts {sum} vs total {total}");
        let params = &j["params"];
        assert!(params["reconstruction_only"].as_u64().unwrap() > 0, "{name}: {params}");

        let gates = j["bridge"]["gates"].as_array().unwrap();
        assert_eq!(gates.len(), 3, "{name}: {gates:?}");
        let mut branches: Vec<&str> = gates.iter().map(|g| g["branch"].as_str().unwrap()).collect();
        branches.sort();
        assert_eq!(branches, ["laplacian", "large", "small"], "{name}");
        for g in gates {
            let want = if g["branch"] == "large" { "k" } else { "1-k" };
            assert_eq!(g["modulation"], want, "{name}: {g}");
            assert!(g["subgraph_nodes"].as_u64().unwrap() >= 3, "{name}: {g}");
        }
        let blur = &j["bridge"]["blur_maps"][0];
        let want_source = if name.contains("_input_") { "input" } else { "constant" };
        assert_eq!(blur["source"], want_source, "{name}");
        assert_eq!(blur["shape"], serde_json::json!([1, 1, 6, 8]), "{name}");

        let want_head = if name.contains("_v5_") { "yolov5-anchor" } else { "yolov8-dfl" };
        assert_eq!(j["head"]["kind"], want_head, "{name}");
        assert_eq!(j["head"]["classes"], 6, "{name}");
        let roles: Vec<&str> = j["outputs"].as_array().unwrap().iter().map(|o| o["role"].as_str().unwrap()).collect();
        assert_eq!(roles, ["reconstruction", "detection"], "{name}");
        assert!(j["warnings"].as_array().unwrap().is_empty(), "{name}: {}", j["warnings"]);
    }
}

#[test]
fn inspect_text_summary_names_the_parts() {
    let f = repo().join("models/fixtures/pdinet_v8_input_op17_nofold.onnx");
    let r = cli(&["inspect", f.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    for needle in ["recon-only", "Yolov8Dfl", "3 gate(s)", "psf_blur"] {
        assert!(r.stdout.contains(needle), "missing {needle:?} in\n{}", r.stdout);
    }
}
