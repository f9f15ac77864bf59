//! The identity pipeline writes a complete output folder whose model runs bit-identically.

use crate::common::*;
use pdi_compile::runtime::{self, Engine};

#[test]
fn identity_compile_writes_folder_and_preserves_outputs() {
    let dir = tempfile::tempdir().unwrap();
    for f in [repo().join("models/fixtures/pdinet_v5_input_op17_nofold.onnx"), repo().join("models/fixtures/pdinet_v8_const_op13_fold.onnx")] {
        let out = dir.path().join(f.file_stem().unwrap());
        let r = cli(&["compile", f.to_str().unwrap(), "--pipeline", "passes/identity.yaml", "-o", out.to_str().unwrap(), "--json"]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
        let on_disk: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
        assert_eq!(report["input_sha256"], on_disk["input_sha256"]);
        assert_eq!(report["before"], report["after"], "identity changes nothing");
        assert_eq!(report["passes"].as_array().unwrap().len(), 0);
        let manifest = std::fs::read_to_string(out.join("manifest.yaml")).unwrap();
        assert!(manifest.contains("input_sha256") && manifest.contains("name: identity"), "{manifest}");
        let leftovers: Vec<_> = std::fs::read_dir(&out).unwrap().map(|e| e.unwrap().file_name()).filter(|n| n.to_string_lossy().ends_with(".tmp")).collect();
        assert!(leftovers.is_empty(), "temp files left: {leftovers:?}");

        let (a, b) = (load(&f), load(&out.join("model.onnx")));
        let inputs = inputs_for(&a, 99);
        let ra = runtime::load(Engine::Ort, &a, &inputs, 1).unwrap().run(&inputs).unwrap();
        let rb = runtime::load(Engine::Ort, &b, &inputs, 1).unwrap().run(&inputs).unwrap();
        for ((n, x), (_, y)) in ra.iter().zip(&rb) {
            assert!(x.bit_identical(y), "{n} differs");
        }
    }
}

#[test]
fn external_data_output_loads_back_identically() {
    let dir = tempfile::tempdir().unwrap();
    let f = repo().join("models/fixtures/pdinet_v8_input_op13_fold.onnx");
    let out = dir.path().join("ext");
    let r = cli(&["compile", f.to_str().unwrap(), "--pipeline", "passes/identity.yaml", "-o", out.to_str().unwrap(), "--external-data"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let small = std::fs::metadata(out.join("model.onnx")).unwrap().len();
    assert!(small < std::fs::metadata(&f).unwrap().len() / 4, "weights moved out ({small} bytes left)");
    assert_eq!(load(&out.join("model.onnx")), load(&f));
}
