//! `pdi-compile ship` (what `scripts/demo` runs) on the trained tiny model, with a recovery
//! budget of seconds: every artifact folder is written, every variant measured, one screen.

use crate::common::*;

#[test]
fn ship_writes_every_artifact_and_one_screen() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ship");
    let r = cli(&["ship", "models/trained/pdinet_v5_tiny_trained.onnx", "--psf", "calib/single_lwir_blur.npy", "--frames", "4", "--recover-steps", "20", "--runs", "2", "-o", out.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    for f in ["f32/model.onnx", "f32/tract.yaml", "pruned-f32/model.onnx", "pruned-f32/tract.yaml", "pruned-int8/model.onnx", "rknn/model.onnx", "rknn/rknn.yaml", "rknn/dataset.txt", "ship.json"] {
        assert!(out.join(f).is_file(), "{f} written");
    }
    assert!(r.stdout.lines().count() <= 34, "one screen:\n{}", r.stdout);
    assert!(r.stdout.contains("pruned-int8") && r.stdout.contains("rknn-convert"), "{}", r.stdout);
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("ship.json")).unwrap()).unwrap();
    let v = report["variants"].as_array().unwrap();
    let names: Vec<&str> = v.iter().map(|v| v["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["original", "f32", "pruned-f32", "pruned-int8"]);
    let macs: Vec<u64> = v.iter().map(|v| v["macs"].as_u64().unwrap()).collect();
    assert!(macs[1] < macs[0] && macs[2] * 10 <= macs[1] * 4, "pruned to about 28% of the compiled MACs: {macs:?}");
    assert!(v[1]["agreement"].as_f64().unwrap() >= 0.99, "the lossless compile agrees: {}", v[1]);
    // INT8 is the pruned model quantized: its MACs and more (the encoder's narrow first blocks
    // run on 2x2 pixel blocks, four times their multiplications), fewer than the unpruned
    // model's; fewer bytes (the layers it keeps in float keep theirs).
    assert!(macs[3] >= macs[2] && macs[3] < 2 * macs[2], "pruned-int8 quantizes pruned-f32: {macs:?}");
    let bytes: Vec<u64> = v.iter().map(|v| v["bytes"].as_u64().unwrap()).collect();
    assert!(bytes[3] < bytes[2] && bytes[2] < bytes[1], "file sizes {bytes:?}");
    for x in &v[1..] {
        assert!(x["ort_ms"].as_f64().unwrap() > 0.0 && x["tract_ms"].as_f64().unwrap() > 0.0, "{x}");
        // Every variant's detections were scored against the original's (20 recovery steps
        // keep little accuracy, but the measurement is there and not nothing).
        let a = x["agreement"].as_f64().unwrap_or_else(|| panic!("{} has no agreement measured: {x}", x["name"]));
        assert!(a > 0.0 && a <= 1.0, "{x}");
    }
    // The artifact to deploy per target, chosen by the measurements above: on a CPU engine the
    // fastest variant keeping 0.9 of the original's accuracy (these frames have no labels, so
    // the agreement), on the RK3588 the RKNN folder.
    let rec = report["recommended"].as_array().unwrap();
    let targets: Vec<&str> = rec.iter().map(|r| r["target"].as_str().unwrap()).collect();
    assert_eq!(targets, ["onnxruntime", "tract", "rk3588"]);
    for (r, key) in rec.iter().zip(["ort_ms", "tract_ms"]) {
        let keeping: Vec<&serde_json::Value> = v[1..].iter().filter(|x| x["agreement"].as_f64().unwrap() >= 0.9).collect();
        let fastest = keeping.iter().min_by(|a, b| a[key].as_f64().unwrap().total_cmp(&b[key].as_f64().unwrap())).unwrap();
        assert_eq!(r["variant"], fastest["name"], "{r}");
        assert!(r["why"].as_str().unwrap().contains(" ms on "), "{r}");
    }
    assert_eq!(rec[2]["variant"], "rknn");
    assert!(r.stdout.contains("deploy\n  onnxruntime  "), "{}", r.stdout);
    // The folders were built beside --out and moved there: their manifests name where their
    // inputs and recipes are now, so a variant built from another one rebuilds.
    for v in ["f32", "pruned-f32", "pruned-int8", "rknn"] {
        let manifest = std::fs::read_to_string(out.join(v).join("manifest.yaml")).unwrap();
        assert!(!manifest.contains(".pdi-partial-"), "{v}'s manifest names the staging folder:\n{manifest}");
        assert!(manifest.contains(&format!("pipeline_file: {}", out.join("recipes").join(format!("{v}.yaml")).display())), "{v}:\n{manifest}");
    }
    let int8 = std::fs::read_to_string(out.join("pruned-int8/manifest.yaml")).unwrap();
    assert!(int8.contains(&format!("input: {}", out.join("pruned-f32/model.onnx").display())), "{int8}");
    let again = dir.path().join("again");
    let r = cli(&["rebuild", out.join("pruned-int8").to_str().unwrap(), "-o", again.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains("model.onnx identical"), "{}", r.stdout);
}
