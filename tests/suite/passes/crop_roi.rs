//! `crop-roi`: the crop keeps every gate map bit for bit and decodes in frame coordinates
//! (through rknn-legalize's split head too); its halos, fitted or trained by `recover`, bring
//! it closer to the full model than zero padding.

use crate::common::*;
use crate::scene::{compile, frames, pass, verify, write, LOSSLESS, MODELS, PSF};
use serde_json::Value;
use pdi_compile::onnx::tensor_proto::to_tensor;
use std::path::Path;

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
    let trained = write(dir.path(), "trained.yaml", &format!("name: trained\npasses: [{LOSSLESS}, {crop}, {{recover: {{train: estimates, steps: 96, frames: 96, batch: 8, lr: 0.003}}}}, cleanup]\n"));
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
