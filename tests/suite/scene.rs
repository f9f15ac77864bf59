//! Scene specialization on the committed trained models: drop-classes is exact, drop-strides
//! removes a scale and keeps the in-range detections, crop-roi crops every gate map bit for
//! bit and decodes in frame coordinates (through rknn-legalize's split head too), and its halos
//! bring it closer to the full model than zero padding.

use crate::common::*;
use pdi_compile::onnx::tensor_proto::to_tensor;
use serde_json::Value;
use std::path::{Path, PathBuf};

const MODELS: [&str; 3] = ["pdinet_v5_tiny_trained.onnx", "pdinet_v5_w0.25_trained.onnx", "pdinet_v8_w0.25_trained.onnx"];
const PSF: &str = "calib/single_lwir_blur.npy";
/// The lossless passes a recipe puts before `crop-roi`.
const LOSSLESS: &str = "strip-recon, bind-psf, fold-constants, fold-psf-gates, fold-bn, dce";

/// 60 held-out frames of the trained models' evaluation recipe (seed 2, 256x192).
fn frames(dir: &Path) -> PathBuf {
    let psf = dir.join("psf");
    let r = cli(&["psf", "simulate", "--lens", "calib/lens_single_lwir.yaml", "-o", psf.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let set = dir.join("eval");
    let r = cli(&["dataset", set.to_str().unwrap(), "--psf", psf.to_str().unwrap(), "--n", "60", "--q", "90", "--seed", "2", "--min-box", "16", "--out-size", "256x192"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    set.join("degraded")
}

fn compile(model: &Path, recipe: &str, scene: Option<&Path>, out: &Path) -> Value {
    let mut args = vec!["compile", model.to_str().unwrap(), "--pipeline", recipe, "--psf", PSF, "-o", out.to_str().unwrap(), "--json"];
    if let Some(s) = scene {
        args.extend(["--scene", s.to_str().unwrap()]);
    }
    let r = cli(&args);
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

fn verify(reference: &Path, candidate: &Path, data: &Path) -> Value {
    let r = cli(&["verify", "--reference", reference.to_str().unwrap(), "--candidate", candidate.to_str().unwrap(), "--psf", PSF, "--data", data.to_str().unwrap(), "--runs", "0", "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

fn pass<'a>(report: &'a Value, name: &str) -> &'a Value {
    report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == name).unwrap_or_else(|| panic!("no {name} pass in {report}"))
}

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

#[test]
fn cropping_keeps_gate_maps_and_frame_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let scene = write(dir.path(), "roi.yaml", "roi: {x: 0, y: 64, w: 256, h: 128}\n");
    // crop-roi placed by the recipe: no recovery is added, and rknn-legalize's decode check
    // (the split head against the in-graph decode, on tract) runs on the cropped grids.
    let recipe = write(dir.path(), "crop.yaml", "name: crop\npasses: [strip-recon, bind-psf, fold-constants, fold-psf-gates, fold-bn, dce, crop-roi, cleanup, rknn-legalize]\n");
    let full_recipe = write(dir.path(), "full.yaml", "name: full\npasses: [strip-recon, bind-psf, fold-constants, fold-psf-gates, fold-bn, dce, cleanup, rknn-legalize]\n");
    for m in MODELS {
        let model = repo().join("models/trained").join(m);
        let (full, cut) = (dir.path().join(format!("{m}.full")), dir.path().join(format!("{m}.cut")));
        let full_report = compile(&model, full_recipe.to_str().unwrap(), None, &full);
        let report = compile(&model, recipe.to_str().unwrap(), Some(&scene), &cut);
        let ratio = report["after"]["macs"].as_f64().unwrap() / full_report["after"]["macs"].as_f64().unwrap();
        assert!(ratio <= 0.70, "{m}: MACs {ratio:.3} of the full model");
        let cropped = pass(&report, "crop-roi")["details"]["constants_cropped"].as_array().unwrap().clone();
        let (a, b) = (load(&full.join("model.onnx")), load(&cut.join("model.onnx")));
        let init = |m: &pdi_compile::onnx::proto::ModelProto, n: &str| m.graph.as_ref().unwrap().initializer.iter().find(|t| t.name == n).map(|t| to_tensor(t).unwrap());
        let mut gates = 0;
        for c in &cropped {
            let name = c[0].as_str().unwrap();
            let Some(f) = init(&a, name).filter(|t| t.shape.len() == 4) else { continue };
            let c = init(&b, name).unwrap();
            let s = 192 / f.shape[2];
            let rows: Vec<usize> = (64 / s..192 / s).collect();
            let want = f.select(2, &rows).unwrap();
            assert!(want.bit_identical(&c), "{m}: gate map {name} is not the full map's crop");
            gates += 1;
        }
        assert!(gates >= 1, "{m}: no gate map cropped: {cropped:?}");
        let layout: Value = serde_json::from_str(&b.metadata_props.iter().find(|p| p.key == "pdi.head_layout").unwrap().value).unwrap();
        assert_eq!(layout["offset"], serde_json::json!([0.0, 64.0]), "{m}: split-head decode offset");
        let meta: Value = serde_json::from_str(&b.metadata_props.iter().find(|p| p.key == "pdi.scene").unwrap().value).unwrap();
        assert_eq!(meta["roi"]["y"], 64);
        // The split head has no output the original has: verify says where it is checked instead.
        let r = cli(&["verify", "--reference", model.to_str().unwrap(), "--candidate", cut.join("model.onnx").to_str().unwrap(), "--psf", PSF, "--random", "1", "--runs", "0"]);
        assert_eq!(r.code, 2, "{m}: {}", r.stderr);
        assert!(r.stderr.trim().lines().count() == 1 && r.stderr.contains("rknn-convert"), "{m}: {}", r.stderr);
    }
}

#[test]
fn halos_bring_the_crop_closer_to_the_full_model() {
    let dir = tempfile::tempdir().unwrap();
    let data = frames(dir.path());
    let scene = write(dir.path(), "roi.yaml", "roi: {x: 0, y: 64, w: 256, h: 128}\n");
    let zero = write(dir.path(), "zero.yaml", &format!("name: zero\npasses: [{LOSSLESS}, {{crop-roi: {{halo: zero}}}}, cleanup]\n"));
    let halo = write(dir.path(), "halo.yaml", &format!("name: halo\npasses: [{LOSSLESS}, crop-roi, cleanup]\n"));
    let agreement = |j: &Value| j["detection"]["agreement"]["map50_95"].as_f64().unwrap();
    let worst = |j: &Value| j["outputs"][0]["groups"].as_array().unwrap().iter().map(|g| g["ort"]["rel_l2"].as_f64().unwrap()).fold(0.0, f64::max);
    for m in MODELS {
        let model = repo().join("models/trained").join(m);
        let (full, a, b) = (dir.path().join(format!("{m}.full")), dir.path().join(format!("{m}.zero")), dir.path().join(format!("{m}.halo")));
        compile(&model, "passes/detect-f32.yaml", None, &full);
        compile(&model, zero.to_str().unwrap(), Some(&scene), &a);
        let report = compile(&model, halo.to_str().unwrap(), Some(&scene), &b);
        let h = &pass(&report, "crop-roi")["details"]["halo"];
        assert!(h["values"].as_u64().unwrap() > 0, "{m}: no halo added: {h}");
        let fit = h["rel_error_vs_zero"]["top"].as_f64().unwrap();
        assert!(fit < 0.6, "{m}: halos no closer than zero padding to the rows above the ROI ({fit:.3})");
        assert!(h["rel_error_vs_zero"].get("bottom").is_none(), "{m}: a halo at the frame's own border: {h}");
        // The bridge's squeeze-excitation pooling: the frame's means estimated from the ROI's.
        let pools = h["pools"].as_array().unwrap();
        assert!(!pools.is_empty() && pools.iter().all(|p| p["rel_error"].as_f64().unwrap() < 0.5), "{m}: {h}");
        let (jz, jh) = (verify(&full.join("model.onnx"), &a.join("model.onnx"), &data), verify(&full.join("model.onnx"), &b.join("model.onnx"), &data));
        println!("{m}: zero padding agreement {:.4} worst rel L2 {:.3}; halos {:.4} {:.3} (rows' error {fit:.3} of zeros')", agreement(&jz), worst(&jz), agreement(&jh), worst(&jh));
        assert!(agreement(&jh) > agreement(&jz) + 0.02, "{m}: halos {:.4} against zero padding {:.4}", agreement(&jh), agreement(&jz));
        assert!(worst(&jh) < worst(&jz), "{m}: worst group error {:.3} with halos, {:.3} without", worst(&jh), worst(&jz));
    }
    // A ROI inside the frame: halos on all four sides (columns over the row halos' corners).
    let boxed = write(dir.path(), "box.yaml", "roi: {x: 64, y: 64, w: 128, h: 96}\n");
    let model = repo().join("models/trained").join(MODELS[1]);
    let full = dir.path().join(format!("{}.full", MODELS[1]));
    let (a, b) = (dir.path().join("box.zero"), dir.path().join("box.halo"));
    compile(&model, zero.to_str().unwrap(), Some(&boxed), &a);
    let report = compile(&model, halo.to_str().unwrap(), Some(&boxed), &b);
    let h = &pass(&report, "crop-roi")["details"]["halo"]["rel_error_vs_zero"];
    for side in ["top", "left", "bottom", "right"] {
        assert!(h[side].as_f64().is_some_and(|e| e < 0.8), "side {side}: {h}");
    }
    // Halos two rows in: a (2 x 1) convolution whose taps run the other way on the far sides.
    let two = write(dir.path(), "two.yaml", &format!("name: two\npasses: [{LOSSLESS}, {{crop-roi: {{halo_rows: 2}}}}, cleanup]\n"));
    let c = dir.path().join("box.two");
    compile(&model, two.to_str().unwrap(), Some(&boxed), &c);
    let full = full.join("model.onnx");
    let (jz, jh, j2) = (verify(&full, &a.join("model.onnx"), &data), verify(&full, &b.join("model.onnx"), &data), verify(&full, &c.join("model.onnx"), &data));
    println!("box ROI: worst rel L2 {:.3} with zero padding, {:.3} with halos, {:.3} two rows in", worst(&jz), worst(&jh), worst(&j2));
    assert!(worst(&jh) < 0.8 * worst(&jz), "box ROI: worst group error {:.3} with halos, {:.3} without", worst(&jh), worst(&jz));
    assert!(worst(&j2) < 0.8 * worst(&jz), "box ROI: worst group error {:.3} with 2-row halos, {:.3} without", worst(&j2), worst(&jz));
}

/// `recover: {train: estimates}` trains the crop's halos and pool corrections alone, end to
/// end against the full model: every other initializer stays bit for bit, and the crop gets
/// closer to the full model on held-out frames. Steps only, no time cap: the same model on any load.
#[test]
fn training_the_estimates_alone_brings_the_crop_closer() {
    let dir = tempfile::tempdir().unwrap();
    let data = frames(dir.path());
    let scene = write(dir.path(), "roi.yaml", "roi: {x: 0, y: 64, w: 256, h: 128}\n");
    // Fitted closed loop (each estimate on the crop's own values), the start training wants.
    let crop = "{crop-roi: {closed_loop: true}}";
    let fitted = write(dir.path(), "fitted.yaml", &format!("name: fitted\npasses: [{LOSSLESS}, {crop}, cleanup]\n"));
    let trained = write(dir.path(), "trained.yaml", &format!("name: trained\npasses: [{LOSSLESS}, {crop}, {{recover: {{train: estimates, steps: 240, frames: 96, batch: 8, lr: 0.003}}}}, cleanup]\n"));
    let model = repo().join("models/trained").join(MODELS[0]);
    let (full, a, b) = (dir.path().join("full"), dir.path().join("fitted"), dir.path().join("trained"));
    compile(&model, "passes/detect-f32.yaml", None, &full);
    let waves = pass(&compile(&model, fitted.to_str().unwrap(), Some(&scene), &a), "crop-roi")["details"]["halo"]["closed_loop_waves"].as_u64().unwrap();
    assert!(waves > 1, "closed loop fitted in {waves} waves");
    let report = compile(&model, trained.to_str().unwrap(), Some(&scene), &b);
    let r = &pass(&report, "recover")["details"];
    assert_eq!(r["train"], "estimates");
    assert_eq!(r["kept"], true, "{r}");
    let t = &r["training"];
    assert!(t["held_out_loss_after"].as_f64().unwrap() < t["held_out_loss_before"].as_f64().unwrap(), "{t}");
    let load = |d: &Path| pdi_compile::onnx::load(&d.join("model.onnx")).unwrap().model.graph.unwrap();
    let (ga, gb) = (load(&a), load(&b));
    let changed: Vec<&str> = ga.initializer.iter().zip(&gb.initializer).filter(|(x, y)| x != y).map(|(x, _)| x.name.as_str()).collect();
    assert_eq!(ga.node, gb.node);
    assert!(!changed.is_empty() && changed.iter().all(|n| n.contains("_halo_") || n.contains("_frame_")), "trained initializers: {changed:?}");
    // The distillation minimises the error over the whole output, so that is what must drop on
    // held-out frames; no scale group may get more than slightly worse on the way.
    let whole = |j: &Value| j["outputs"][0]["ort"]["rel_l2"].as_f64().unwrap();
    let worst = |j: &Value| j["outputs"][0]["groups"].as_array().unwrap().iter().map(|g| g["ort"]["rel_l2"].as_f64().unwrap()).fold(0.0, f64::max);
    let (ja, jb) = (verify(&full.join("model.onnx"), &a.join("model.onnx"), &data), verify(&full.join("model.onnx"), &b.join("model.onnx"), &data));
    println!("rel L2 fitted {:.4} (worst group {:.4}); trained {:.4} (worst group {:.4})", whole(&ja), worst(&ja), whole(&jb), worst(&jb));
    assert!(whole(&jb) < whole(&ja), "trained estimates: rel L2 {:.4} against fitted {:.4}", whole(&jb), whole(&ja));
    assert!(worst(&jb) < 1.05 * worst(&ja), "trained estimates: worst group {:.4} against fitted {:.4}", worst(&jb), worst(&ja));
    // Without a crop before it there is nothing to train.
    let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", trained.to_str().unwrap(), "--psf", PSF, "-o", dir.path().join("none").to_str().unwrap()]);
    assert_eq!(r.code, 2, "{}", r.stderr);
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
        assert!((0.0..=1.0).contains(&a), "{m}: {c}");
        agreement.push(a);
    }
    assert!(agreement[0] < 0.98 && agreement[0] < agreement[1], "tiny {} against v8 {}", agreement[0], agreement[1]);

    let out = dir.path().join("tiny");
    compile(&repo().join("models/trained").join(MODELS[0]), "passes/detect-f32.yaml", None, &out);
    let whole = pdi_compile::scene::Roi { x: 0, y: 0, w: 256, h: 192 };
    let c = pdi_compile::scene::context::measure(&load(&out.join("model.onnx")), whole, None, 8, 0, 1).unwrap().expect("the tiny has a decoded YOLOv5 output");
    assert!(c.reference_boxes > 0 && c.agreement == 1.0, "{c:?}");
}
