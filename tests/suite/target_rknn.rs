//! The RKNN target: `--target rknn` writes what the toolkit needs, and `rknn-convert` builds
//! it with RKNN-Toolkit2 2.5.0 and checks its simulator. The RKNN passes have their own
//! files: `passes::rknn_legalize`, `passes::rknn_hybrid`, `passes::rknn_qat`.

use crate::common::*;

pub(crate) fn compile(model: &str, pipeline: &str, out: &std::path::Path, extra: &[&str]) -> CliResult {
    let mut args = vec!["compile", model, "--pipeline", pipeline, "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()];
    args.extend(extra);
    cli(&args)
}

#[test]
fn rknn_target_writes_config_dataset_and_frames() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rknn");
    let r = compile("models/fixtures/pdinet_v8_const_op13_fold.onnx", "passes/detect-rknn.yaml", &out, &["--target", "rknn"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let config: serde_json::Value = yaml_serde::from_str(&std::fs::read_to_string(out.join("rknn.yaml")).unwrap()).unwrap();
    assert_eq!(config["target_platform"], "rk3588");
    assert_eq!(config["outputs"].as_array().unwrap().len(), 9, "boxes, scores, score_sum × 3 strides");
    assert_eq!(config["input"]["std_values"][0][0], 255.0);
    assert_eq!(config["input"]["range"], serde_json::json!([0.0, 1.0]), "every 8-bit pixel on its own int8 step");
    let lines: Vec<String> = std::fs::read_to_string(out.join("dataset.txt")).unwrap().lines().map(String::from).collect();
    assert_eq!(lines.len(), config["quantization"]["dataset_frames"].as_u64().unwrap() as usize);
    let frame = pdi_compile::optics::npy::read(&out.join(&lines[0])).unwrap();
    assert_eq!(frame.shape, vec![1, 1, 192, 256]);
    assert!(frame.data.iter().all(|&p| (0.0..=255.0).contains(&p) && p == p.round()), "8-bit pixel values");
    assert!(frame.data.iter().any(|&p| p > 16.0), "not a blank frame");
    assert!(std::fs::read_to_string(out.join("manifest.yaml")).unwrap().contains("target: rknn"));
}

#[test]
fn rknn_target_refuses_models_it_cannot_take() {
    let dir = tempfile::tempdir().unwrap();
    // No rknn-legalize in the recipe: the decode is still in the graph.
    let out = dir.path().join("decoded");
    let r = compile("models/fixtures/pdinet_v5_input_op17_nofold.onnx", "passes/detect-f32.yaml", &out, &["--target", "rknn"]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("rknn-legalize") && r.stderr.lines().count() == 1, "{}", r.stderr);
    assert!(!out.join("model.onnx").exists(), "no half-written folder");
    // Opset above what the toolkit reads.
    let mut m = load(&repo().join("models/fixtures/pdinet_v5_const_op17_fold.onnx"));
    m.opset_import.iter_mut().for_each(|o| o.version = 21);
    let high = dir.path().join("op21.onnx");
    pdi_compile::onnx::save(&m, &high).unwrap();
    let r = compile(high.to_str().unwrap(), "passes/detect-rknn.yaml", &dir.path().join("op21"), &[]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("opset ≤ 19") && r.stderr.contains("21"), "{}", r.stderr);
}

/// RKNN-Toolkit2 2.5.0 builds the trained model and its simulator agrees with ORT (installs
/// the toolkit into the cache on first use: the test never skips).
#[test]
fn rknn_convert_builds_and_its_simulator_agrees_with_ort() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rknn");
    let r = compile("models/trained/pdinet_v5_tiny_trained.onnx", "passes/detect-rknn.yaml", &out, &["--target", "rknn"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let r = cli(&["rknn-convert", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}\n{}", r.stdout, r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    println!("{report:#}");
    assert!(out.join("model.rknn").metadata().unwrap().len() > 10_000);
    assert!(!out.join("check0_base_optimize.onnx").exists(), "the toolkit's debug dumps are not left in the artifact");
    assert_eq!(report["cpu_layers"].as_array().unwrap().len(), 0);
    assert!(report["npu_layers"].as_u64().unwrap() > 50);
    assert!(report["quantization"].as_str().unwrap().ends_with("the input over [0, 1]"), "{}", report["quantization"]);
    for a in report["outputs"].as_array().unwrap().iter().chain(report["groups"].as_array().unwrap()) {
        assert!(a["cosine"].as_f64().unwrap() >= 0.99, "{a}");
    }
    let names: Vec<&str> = report["groups"].as_array().unwrap().iter().map(|g| g["name"].as_str().unwrap()).collect();
    assert_eq!(names, ["objectness", "classes"]);
    let (found, matched) = (report["detections_ort"].as_u64().unwrap(), report["detections_matched"].as_u64().unwrap());
    assert!(found > 0 && matched as f64 >= 0.9 * found as f64, "{matched} of {found}");
    // A gate it cannot meet fails with exit 1 and says why.
    let r = cli(&["rknn-convert", out.to_str().unwrap(), "--min-cosine", "0.999999"]);
    assert_eq!(r.code, 1, "{}", r.stdout);
    assert!(r.stdout.contains("FAIL") && r.stdout.contains("cosine"), "{}", r.stdout);
}

/// `detect-rknn` with `pass` after it, written into `dir`.
pub(crate) fn detect_rknn_then(dir: &std::path::Path, pass: &str) -> std::path::PathBuf {
    let recipe = dir.join("detect-rknn-then.yaml");
    std::fs::write(&recipe, format!("name: detect-rknn-then\nbase: detect-rknn\npasses:\n  - {pass}\n")).unwrap();
    recipe
}
