//! `verify` as a CI gate: exit 0 when thresholds hold, 1 on a regression, 2 on bad input.

use crate::common::*;
use pdi_compile::onnx::tensor_proto::{from_tensor, to_tensor};
use pdi_compile::tensor::Tensor;
use std::path::{Path, PathBuf};

fn compiled(dir: &Path, fixture: &str) -> (PathBuf, PathBuf) {
    let f = repo().join("models/fixtures").join(fixture);
    let out = dir.join(fixture);
    let r = cli(&["compile", f.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", "calib/radial_6x8.npy", "-o", out.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    (f, out.join("model.onnx"))
}

/// The shipped gate without its latency line: timing belongs in benchmarks, not in tests.
fn accuracy_gate(dir: &Path) -> PathBuf {
    let text = std::fs::read_to_string(repo().join("passes/gate.yaml")).unwrap();
    assert!(text.contains("max_latency_ratio"), "the shipped gate checks latency");
    let p = dir.join("accuracy-gate.yaml");
    std::fs::write(&p, text.lines().filter(|l| !l.starts_with("max_latency_ratio")).collect::<Vec<_>>().join("\n")).unwrap();
    p
}

fn verify(reference: &Path, candidate: &Path, extra: &[&str]) -> CliResult {
    let gate = accuracy_gate(candidate.parent().unwrap());
    let mut args = vec!["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", "calib/radial_6x8.npy", "--gate", gate.to_str().unwrap(), "--random", "3", "--runs", "3", "--json"];
    args.extend_from_slice(extra);
    cli(&args)
}

#[test]
fn lossless_compile_passes_the_gate() {
    let dir = tempfile::tempdir().unwrap();
    let (reference, candidate) = compiled(dir.path(), "pdinet_v8_input_op17_nofold.onnx");
    // Synthetic frames carry no labels: the drop against labels cannot be measured, and the
    // gate says so instead of passing it.
    let r = verify(&reference, &candidate, &[]);
    assert_eq!(r.code, 1, "{}\n{}", r.stdout, r.stderr);
    let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let unmeasured: Vec<&serde_json::Value> = j["checks"].as_array().unwrap().iter().filter(|c| c["value"].is_null()).collect();
    assert_eq!(unmeasured.len(), 1, "{}", j["checks"]);
    assert_eq!((unmeasured[0]["key"].as_str(), unmeasured[0]["passed"].as_bool()), (Some("max_map_drop"), Some(false)));
    assert!(unmeasured[0]["unmeasured"].as_str().unwrap().contains("no labels"), "{}", unmeasured[0]);
    let screen = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", "calib/radial_6x8.npy", "--gate", accuracy_gate(dir.path()).to_str().unwrap(), "--random", "1", "--runs", "0"]);
    assert_eq!(screen.code, 1);
    assert!(screen.stdout.contains("[FAIL: not measured] mAP@.5:.95 drop against labels") && screen.stdout.contains("--allow-unmeasured max_map_drop"), "{}", screen.stdout);
    // Named, it passes, and says it was allowed.
    let r = verify(&reference, &candidate, &["--allow-unmeasured", "max_map_drop"]);
    assert_eq!(r.code, 0, "{}\n{}", r.stdout, r.stderr);
    let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert_eq!(j["passed"], true);
    assert!(j["checks"].as_array().unwrap().iter().any(|c| c["key"] == "max_map_drop" && c["allowed"] == true), "{}", j["checks"]);
    // A misspelt key allows nothing: refused.
    let r = verify(&reference, &candidate, &["--allow-unmeasured", "max_map_dorp"]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("not a gate key"), "{}", r.stderr);
    let out = &j["outputs"][0];
    assert_eq!(out["name"], "detections");
    let groups: Vec<&str> = out["groups"].as_array().unwrap().iter().map(|g| g["group"].as_str().unwrap()).collect();
    assert_eq!(groups, ["boxes", "classes"]);
    assert!(out["tract"]["rel_l2"].as_f64().unwrap() < 1e-4);
    assert!((j["detection"]["agreement"]["map50_95"].as_f64().unwrap() - 1.0).abs() < 1e-9);
    assert_eq!(j["latency"].as_array().unwrap().len(), 3, "reference/ort, candidate/ort, candidate/tract");
}

#[test]
fn a_perturbed_candidate_fails_with_exit_1() {
    let dir = tempfile::tempdir().unwrap();
    let (reference, candidate) = compiled(dir.path(), "pdinet_v5_const_op17_fold.onnx");
    let mut m = load(&candidate);
    let g = m.graph.as_mut().unwrap();
    // Nudge the last head conv's weights by 1%: small, but far above rounding noise.
    let last_conv = g.node.iter().rev().find(|n| n.op_type == "Conv").unwrap().input[1].clone();
    let w = g.initializer.iter_mut().find(|t| t.name == last_conv).unwrap();
    let t = to_tensor(w).unwrap();
    let v: Vec<f32> = t.as_f32().unwrap().iter().map(|x| x * 1.01).collect();
    *w = from_tensor(&last_conv, &Tensor::f32(t.shape.clone(), v));
    let bad = dir.path().join("perturbed.onnx");
    pdi_compile::onnx::save(&m, &bad).unwrap();
    let junit = dir.path().join("gate-junit.xml");
    let r = verify(&reference, &bad, &["--no-tract", "--junit", junit.to_str().unwrap(), "--allow-unmeasured", "max_map_drop,max_rel_l2_tract"]);
    assert_eq!(r.code, 1, "{}\n{}", r.stdout, r.stderr);
    // The JUnit report names the failed checks for CI dashboards.
    let xml = std::fs::read_to_string(&junit).unwrap();
    assert!(xml.contains("<failure message=") && xml.contains("rel L2"), "{xml}");
    assert!(xml.contains("<skipped message=\"not measured (tract was not run (--no-tract))"), "{xml}");
    let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let failed: Vec<&str> = j["checks"].as_array().unwrap().iter().filter(|c| c["passed"] == false).map(|c| c["name"].as_str().unwrap()).collect();
    assert!(failed.iter().any(|n| n.contains("rel L2")), "{failed:?}");
}

#[test]
fn bad_verify_input_exits_2() {
    let dir = tempfile::tempdir().unwrap();
    let (reference, candidate) = compiled(dir.path(), "pdinet_v5_input_op13_fold.onnx");
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--random", "1", "--runs", "1"]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("--psf"), "{}", r.stderr);
    let gate = dir.path().join("gate.yaml");
    std::fs::write(&gate, "max_rel_l2: 1e-5\nmax_typo: 3\n").unwrap();
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", "calib/radial_6x8.npy", "--gate", gate.to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("max_typo"), "{}", r.stderr);
    // --runs 0 measures accuracy only: a gate on latency cannot be checked then.
    std::fs::write(&gate, "max_rel_l2: 1e-5\nmax_latency_ratio: 1.1\n").unwrap();
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", "calib/radial_6x8.npy", "--gate", gate.to_str().unwrap(), "--runs", "0"]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("--runs"), "{}", r.stderr);
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", "calib/radial_6x8.npy", "--random", "1", "--runs", "0", "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert!(j["latency"].as_array().unwrap().is_empty() && j["latency_ratio"].is_null(), "{j}");
}

/// Frames from a folder (16-bit PNG) with YOLO labels: both models are scored against them.
#[test]
fn labelled_frames_give_map_against_labels() {
    let dir = tempfile::tempdir().unwrap();
    let (reference, candidate) = compiled(dir.path(), "pdinet_v5_const_op13_nofold.onnx");
    let data = dir.path().join("frames");
    std::fs::create_dir(&data).unwrap();
    for (k, f) in pdi_compile::frames::synthetic(3, 192, 256, 5).iter().enumerate() {
        let px: Vec<u16> = f.image.as_f32().unwrap().iter().map(|v| (v * 65535.0) as u16).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(256, 192, px).unwrap().save(data.join(format!("f{k}.png"))).unwrap();
        std::fs::write(data.join(format!("f{k}.txt")), "0 0.5 0.6 0.1 0.2\n2 0.25 0.7 0.05 0.05\n").unwrap();
    }
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--data", data.to_str().unwrap(), "--runs", "2", "--no-tract", "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let j: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert_eq!(j["frames"], 3);
    let (a, b) = (&j["detection"]["reference_vs_labels"], &j["detection"]["candidate_vs_labels"]);
    assert!(a["map50"].is_number() && b["map50"].is_number(), "{}", j["detection"]);
    assert!((a["map50_95"].as_f64().unwrap() - b["map50_95"].as_f64().unwrap()).abs() < 1e-3);
}

/// After `scripts/setup` (the demo, the tests) a bare `pdi-compile` finds ONNX Runtime in the
/// cache, with neither `PDI_ORT_LIB` nor `PDI_PYTHON` set; with no cache (and no `python3` with onnxruntime) it says how to set up.
#[test]
fn a_bare_binary_finds_onnx_runtime_in_the_cache() {
    let cache = std::env::var("PDI_CACHE").expect("PDI_CACHE is not set: run the suite with scripts/test, which installs ONNX Runtime into the cache");
    let run = |cache: &str, path: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_pdi-compile"))
            .args(["verify", "--reference", "models/trained/pdinet_v5_tiny_trained.onnx", "--candidate", "models/trained/pdinet_v5_tiny_trained.onnx", "--psf", "calib/single_lwir_blur.npy", "--random", "1", "--runs", "0", "--no-tract"])
            .current_dir(repo())
            .env_remove("PDI_ORT_LIB")
            .env_remove("PDI_PYTHON")
            .env("PDI_CACHE", cache)
            .env("PATH", path)
            .output()
            .unwrap()
    };
    let found = run(&cache, &std::env::var("PATH").unwrap_or_default());
    assert!(found.status.success(), "{}", String::from_utf8_lossy(&found.stderr));
    // No cache and no python3 to ask either.
    let missing = run("/nonexistent-pdi-cache", "/nonexistent-bin");
    let stderr = String::from_utf8_lossy(&missing.stderr);
    assert_eq!(missing.status.code(), Some(2), "{stderr}");
    assert!(stderr.contains("scripts/setup") && stderr.trim().lines().count() == 1, "{stderr}");
}
