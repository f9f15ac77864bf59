//! Scene specialization: bad scene files are refused, and `inspect --scene` measures what an
//! ROI owes to the outside. The scene passes have their own files (`passes::drop_classes`,
//! `passes::drop_strides`, `passes::crop_roi`); the helpers here serve them.

use crate::common::*;
use serde_json::Value;
use std::path::{Path, PathBuf};

pub(crate) const MODELS: [&str; 3] = ["pdinet_v5_tiny_trained.onnx", "pdinet_v5_w0.25_trained.onnx", "pdinet_v8_w0.25_trained.onnx"];
pub(crate) const PSF: &str = "calib/single_lwir_blur.npy";
/// The lossless passes a recipe puts before `crop-roi`.
pub(crate) const LOSSLESS: &str = "strip-recon, bind-psf, fold-constants, fold-psf-gates, fold-bn, dce";

/// 60 held-out frames of the trained models' evaluation recipe (seed 2, 256x192), shared.
pub(crate) fn frames(dir: &Path) -> PathBuf {
    eval_frames(dir, 60)
}

pub(crate) fn compile(model: &Path, recipe: &str, scene: Option<&Path>, out: &Path) -> Value {
    let mut args = vec!["compile", model.to_str().unwrap(), "--pipeline", recipe, "--psf", PSF, "-o", out.to_str().unwrap(), "--json"];
    if let Some(s) = scene {
        args.extend(["--scene", s.to_str().unwrap()]);
    }
    let r = cli(&args);
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

/// On ONNX Runtime alone: the scene passes' claims are ONNX Runtime's figures, and tract's run
/// of each candidate doubled the time of every comparison.
pub(crate) fn verify(reference: &Path, candidate: &Path, data: &Path) -> Value {
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", PSF, "--data", data.to_str().unwrap(), "--runs", "0", "--no-tract", "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

pub(crate) fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

pub(crate) fn pass<'a>(report: &'a Value, name: &str) -> &'a Value {
    report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == name).unwrap_or_else(|| panic!("no {name} pass in {report}"))
}

#[test]
fn bad_scenes_are_refused_with_one_line() {
    let dir = tempfile::tempdir().unwrap();
    let model = repo().join("models/trained/pdinet_v5_tiny_trained.onnx");
    for (text, says) in [("classes: [Boat]\n", "Boat"), ("roi: {x: 0, y: 60, w: 256, h: 128}\n", "multiples of 32"), ("object_px: [30, 10]\n", "object_px"), ("colour: red\n", "colour")] {
        let scene = write(dir.path(), "bad.yaml", text);
        let out = dir.path().join("out");
        let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", PSF, "--scene", scene.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{text}: {}", r.stderr);
        assert_eq!(r.stderr.trim().lines().count(), 1, "{text}: {}", r.stderr);
        assert!(r.stderr.contains(says), "{text}: {}", r.stderr);
        assert!(!out.join("model.onnx").exists(), "{text}: wrote a model");
    }
}

/// `inspect --scene` with an ROI measures how much the lossless model's detections inside it
/// depend on the pixels outside it (each frame's outside swapped with the next frame's): the
/// tiny model, whose crop stays furthest from it (README), depends on them more than the v8;
/// and an ROI that is the whole frame leaves nothing to swap, so it agrees exactly.
#[test]
fn the_preview_measures_what_the_roi_owes_to_the_outside() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write(dir.path(), "roi.yaml", "roi: {x: 0, y: 64, w: 256, h: 128}\n");
    let mut agreement = Vec::new();
    for m in [MODELS[0], MODELS[2]] {
        let model = repo().join("models/trained").join(m);
        let r = cli(&["inspect", model.to_str().unwrap(), "--scene", scene.to_str().unwrap(), "--psf", PSF, "--json"]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let c = &serde_json::from_str::<Value>(&r.stdout).unwrap()["context"];
        let (a, boxes) = (c["agreement"].as_f64().unwrap(), c["reference_boxes"].as_u64().unwrap());
        println!("{m}: ROI detections with the outside swapped agree {a:.4} ({boxes} boxes)");
        assert!(boxes >= 20, "{m}: {c}");
        agreement.push(a);
    }
    // Measured on these simulated frames: tiny 0.677, v8 0.996 (docs/results/scene.md).
    assert!(agreement[0] < 0.9 && agreement[1] >= 0.95, "tiny {} (owes much to the outside), v8 {} (little)", agreement[0], agreement[1]);

    let out = dir.path().join("tiny");
    compile(&repo().join("models/trained").join(MODELS[0]), "passes/detect-f32.yaml", None, &out);
    let whole = pdi_compile::scene::Roi { x: 0, y: 0, w: 256, h: 192 };
    let c = pdi_compile::scene::context::measure(&load(&out.join("model.onnx")), whole, None, 8, 0, 1).unwrap().expect("the tiny has a decoded YOLOv5 output");
    assert!(c.reference_boxes > 0 && c.agreement == 1.0, "{c:?}");
}
