//! Recovery by distillation: the torch interpreter agrees with ONNX Runtime op by op, and the
//! `recover` pass brings a pruned model closer to the unpruned one without touching its graph.
//! Needs the cache's torch venv: `pdi_compile::pyenv` installs it on first use (never skips).

use crate::common::*;
use pdi_compile::tensor::Tensor;

fn frames(shape: [usize; 4], n: usize) -> Vec<Tensor> {
    let mut rng = Lcg(7);
    (0..n).map(|_| Tensor::f32(shape.to_vec(), (0..shape.iter().product()).map(|_| rng.next_f32()).collect())).collect()
}

fn compile(model: &str, recipe: &str, out: &std::path::Path) -> serde_json::Value {
    let r = cli(&["compile", model, "--pipeline", recipe, "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

/// Runs `models/pdinet/export.py` with `args` from the repository root (in the cache's torch
/// venv); fails the test on its error.
fn export_pdinet(args: &[&str]) {
    let out = std::process::Command::new(pdi_compile::pyenv::torch_python().unwrap()).current_dir(repo()).arg("models/pdinet/export.py").args(args).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

const LOSSLESS: &str = "strip-recon, bind-psf, fold-constants, fold-psf-gates, fold-bn, resize-to-deconv, dce";

/// Every op the compiler emits for both heads, pruned or not, float or INT8 (QDQ as
/// quantization-aware recovery trains it: without space-to-depth's blocks, which the pipeline
/// lowers before it), split for the NPU (rknn-qat trains it), computed by
/// the worker's torch interpreter within 1e-4 of ONNX Runtime (on each value's scale, each
/// node fed ORT's own inputs); the Conv forms it trains faster than plain torch (image stem
/// as columns, the large depthwise kernel's own weight gradient) within 1e-4 of torch's
/// gradients.
#[test]
fn the_interpreter_matches_onnx_runtime_op_by_op() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("pruned.yaml");
    std::fs::write(&recipe, format!("name: t\npasses: [{LOSSLESS}, {{prune: {{ratio: 0.5, compensate: none}}}}, cleanup]\n")).unwrap();
    let int8 = dir.path().join("int8.yaml");
    std::fs::write(&int8, recipe_edit("passes/detect-int8.yaml", SPACE_TO_DEPTH, "")).unwrap();
    for (model, recipe) in [("models/trained/pdinet_v5_w0.25_trained.onnx", recipe.to_str().unwrap()), ("models/trained/pdinet_v8_w0.25_trained.onnx", "passes/detect-f32.yaml"), ("models/trained/pdinet_v5_tiny_trained.onnx", int8.to_str().unwrap()), ("models/trained/pdinet_v8_w0.25_trained.onnx", "passes/detect-rknn.yaml")] {
        let out = dir.path().join(model.replace('/', "_"));
        compile(model, recipe, &out);
        let mut m = load(&out.join("model.onnx"));
        // Training sees 2-D convolutions: the pipeline lowers narrow-convs-nchw's 3-D ones
        // before any pass that does not take them (detect-int8 ends with that pass).
        pdi_compile::ir::rewrite::conv_3d::lower_all(m.graph.as_mut().unwrap()).unwrap();
        let check = pdi_compile::torch::train::check_ops(&m, &frames([1, 1, 192, 256], 2)).unwrap();
        println!("{model}: {check:?}");
        let ops = check.ops;
        // Every model here has an image stem and the PSF's 15x15 depthwise kernel.
        assert_eq!(check.gradients.keys().map(String::as_str).collect::<Vec<_>>(), ["columns", "depthwise"], "{model}: both trained Conv forms are checked");
        for (form, err) in &check.gradients {
            assert!(*err <= 1e-4, "{model}: Conv gradients as {form} differ from torch's by {err}");
        }
        let emitted: std::collections::BTreeSet<&str> = m.graph.as_ref().unwrap().node.iter().map(|n| n.op_type.as_str()).collect();
        assert_eq!(ops.keys().map(String::as_str).collect::<std::collections::BTreeSet<_>>(), emitted, "every emitted op is checked");
        for (op, err) in &ops {
            assert!(*err <= 1e-4, "{model}: {op} differs from ONNX Runtime by {err}");
        }
    }
}

/// The features distilled beside the logits: on the compiled v8 the head's last inputs and the
/// three neck outputs its box and class branches start from; on the v5, whose head reads the
/// neck outputs directly, those three alone.
#[test]
fn features_reach_back_to_where_yolov8_branches_start() {
    let dir = tempfile::tempdir().unwrap();
    for (model, total) in [("models/trained/pdinet_v8_w0.25_trained.onnx", 9), ("models/trained/pdinet_v5_w0.25_trained.onnx", 3)] {
        let out = dir.path().join(model.replace('/', "_"));
        compile(model, "passes/detect-f32.yaml", &out);
        let features: Vec<String> = pdi_compile::torch::heads::feature_specs(&load(&out.join("model.onnx")), &Default::default()).unwrap().iter().map(|f| f["value"].as_str().unwrap().to_string()).collect();
        let necks = features.iter().filter(|v| v.starts_with("/neck/")).count();
        assert_eq!((features.len(), necks), (total, 3), "{model}: {features:?}");
    }
}

/// What the worker labels a student with (`pseudo.py`) is the detector's own output: on the
/// compiled v8, the teacher's detections from its head convolutions are `run`'s (the same
/// classes, boxes within 0.01 px) at the worker's score threshold and NMS IoU; and YOLOv8's
/// loss against them is lower for the teacher than for the teacher with its box logits
/// disturbed.
#[test]
fn the_teacher_labels_its_student_with_its_own_detections() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("v8");
    compile("models/trained/pdinet_v8_w0.25_trained.onnx", "passes/detect-f32.yaml", &out);
    let model = out.join("model.onnx");
    let heads = pdi_compile::torch::heads::head_specs(&load(&model)).unwrap();
    let frames: Vec<_> = pdi_compile::deploy::image::list(&eval_frames(dir.path(), 4)).unwrap();
    let work = dir.path().join("work");
    pdi_compile::torch::write_scripts(&work).unwrap();
    let config = serde_json::json!({"model": model, "heads": heads, "frames": frames});
    std::fs::write(work.join("config.json"), config.to_string()).unwrap();
    let script = r#"
import json, sys
import numpy as np, onnx, torch
from PIL import Image
import pseudo
from interpreter import Graph
cfg = json.load(open("config.json"))
heads = cfg["heads"]
g = Graph(onnx.load(cfg["model"]), trainable=False).eval()
x = torch.from_numpy(np.stack([np.asarray(Image.open(f), dtype=np.float32)[None] / 65535.0 for f in cfg["frames"]]))
with torch.no_grad():
    ts = g(x, [h["value"] for h in heads])
pairs = pseudo.levels(ts, heads)
nc, reg_max = ts[pairs[0][1]].shape[1], heads[pairs[0][0]]["reg_max"]
found, size = pseudo.labels(pseudo.per_level(ts, pairs), nc, reg_max)
norm = lambda t: t.sum().clamp(min=1)
disturbed = [t + 0.5 * torch.randn(t.shape, generator=torch.Generator().manual_seed(0)) if h["kind"] == "v8box" else t for t, h in zip(ts, heads)]
print(json.dumps({"labels": found.tolist(), "size": size, "own": float(pseudo.loss(ts, ts, heads, norm)), "disturbed": float(pseudo.loss(disturbed, ts, heads, norm))}))
"#;
    std::fs::write(work.join("check.py"), script).unwrap();
    let run = std::process::Command::new(pdi_compile::pyenv::torch_python().unwrap()).current_dir(&work).arg("check.py").output().unwrap();
    assert!(run.status.success(), "{}", String::from_utf8_lossy(&run.stderr));
    let got: serde_json::Value = serde_json::from_slice(&run.stdout).unwrap();
    println!("{got}");
    let (w, h) = (got["size"][0].as_f64().unwrap(), got["size"][1].as_f64().unwrap());
    assert_eq!((w, h), (256.0, 192.0));
    let labels: Vec<Vec<f64>> = serde_json::from_value(got["labels"].clone()).unwrap();
    let opts = pdi_compile::deploy::Options { conf: Some(0.25), iou: Some(0.7), ..Default::default() };
    let mut detector = pdi_compile::deploy::Detector::load_with(&model, &opts).unwrap();
    let mut total = 0;
    for (i, f) in frames.iter().enumerate() {
        let mut want = detector.detect(&pdi_compile::deploy::image::Image::read(f).unwrap()).unwrap();
        let mut have: Vec<&Vec<f64>> = labels.iter().filter(|l| l[0] == i as f64).collect();
        assert_eq!(have.len(), want.len(), "frame {i}: {have:?} against {want:?}");
        // Both lists in one order: by class, then left edge.
        want.sort_by(|a, b| (a.class, a.bbox[0]).partial_cmp(&(b.class, b.bbox[0])).unwrap());
        have.sort_by(|a, b| (a[1], a[2] - a[4] / 2.0).partial_cmp(&(b[1], b[2] - b[4] / 2.0)).unwrap());
        for (l, d) in have.iter().zip(&want) {
            let corners = [(l[2] - l[4] / 2.0) * w, (l[3] - l[5] / 2.0) * h, (l[2] + l[4] / 2.0) * w, (l[3] + l[5] / 2.0) * h];
            assert_eq!(l[1] as usize, d.class, "frame {i}");
            for (a, b) in corners.iter().zip(d.bbox) {
                assert!((a - b as f64).abs() < 0.01, "frame {i}: {corners:?} against {:?}", d.bbox);
            }
        }
        total += want.len();
    }
    assert!(total >= 4, "the frames hold objects the teacher finds ({total})");
    let (own, disturbed) = (got["own"].as_f64().unwrap(), got["disturbed"].as_f64().unwrap());
    assert!(own.is_finite() && own < disturbed, "the teacher fits its own labels best: {own} against {disturbed}");
}

/// A short recovery of the pruned tiny model: held-out agreement with the unpruned model gets
/// better, the node list stays exactly what `prune` left.
#[test]
fn recovery_improves_agreement_and_keeps_the_nodes() {
    let dir = tempfile::tempdir().unwrap();
    let prune = "{prune: {ratio: 0.5, compensate: none}}";
    let (plain, recovered) = (dir.path().join("plain.yaml"), dir.path().join("recovered.yaml"));
    std::fs::write(&plain, format!("name: p\npasses: [{LOSSLESS}, {prune}, cleanup]\n")).unwrap();
    std::fs::write(&recovered, format!("name: r\npasses: [{LOSSLESS}, {prune}, {{recover: {{steps: 72, frames: 96, batch: 8, ema: 0.9, v5_box_edges: 8}}}}, cleanup]\n")).unwrap();
    let model = "models/trained/pdinet_v5_tiny_trained.onnx";
    compile(model, plain.to_str().unwrap(), &dir.path().join("plain"));
    let report = compile(model, recovered.to_str().unwrap(), &dir.path().join("recovered"));
    let r = &report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "recover").unwrap()["details"];
    println!("{}", serde_json::to_string_pretty(r).unwrap());
    let worst = |m: &serde_json::Value| m.as_object().unwrap().iter().filter(|(k, _)| k.contains('/')).map(|(_, v)| v.as_f64().unwrap()).fold(0.0, f64::max);
    let (before, after) = (worst(&r["output_rel_l2"]["before"]), worst(&r["output_rel_l2"]["after"]));
    assert!(after < before, "recovery improves the worst output group: {before} -> {after}");
    assert_eq!(r["kept"], true);
    let (a0, a1) = (r["detection_agreement"]["before"].as_f64().unwrap(), r["detection_agreement"]["after"].as_f64().unwrap());
    assert!(a1 > a0, "the detections agree better with the unpruned model's: {a0} -> {a1}");
    // The weights' average replaces the last step's only where the held-out loss says so.
    let ema = &r["training"]["ema"];
    let (last, average) = (ema["held_out_loss_last"].as_f64().unwrap(), ema["held_out_loss_average"].as_f64().unwrap());
    assert_eq!(ema["kept"], average < last, "{ema}");
    assert_eq!(r["training"]["held_out_loss_after"].as_f64().unwrap(), last.min(average), "{ema}");
    assert!(r["training"]["steps"].as_u64().unwrap() > 0 && r["training"]["frames_per_second"].as_f64().unwrap() > 0.0);
    assert_eq!(r["v5_box_edges"], 8.0, "the YOLOv5 box sides' term trained with the rest");
    let nodes = |p: &str| load(&dir.path().join(p).join("model.onnx")).graph.unwrap().node;
    assert_eq!(nodes("plain"), nodes("recovered"), "recovery changes weights only");
}

/// Recovery without a prune pass before it is refused with one clear line.
#[test]
fn recover_needs_a_prune_pass() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("r.yaml");
    std::fs::write(&recipe, format!("name: r\npasses: [{LOSSLESS}, recover]\n")).unwrap();
    let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", dir.path().join("o").to_str().unwrap()]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("recover: needs teacher from an earlier pass: put prune") && r.stderr.trim().lines().count() == 1, "{}", r.stderr);
    assert!(!dir.path().join("o/model.onnx").exists(), "nothing written");
}

/// Impossible recovery settings are refused in one line before any training, and nothing is
/// written.
#[test]
fn impossible_recover_settings_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let weights = "box_edges, class_foreground, v5_box_edges, box_iou and pseudo_labels must be finite and 0 or more";
    for (setting, needle) in [("box_edges: -1", weights), ("v5_box_edges: -0.5", weights), ("box_edges: .inf", weights), ("class_foreground: -2", weights), ("class_foreground: .nan", weights), ("box_iou: -1", weights), ("pseudo_labels: .nan", weights), ("lr: .nan", "lr must be a positive number"), ("batch: 0", "steps and batch must be at least 1"), ("devices: 0", "devices must be 1 to 64"), ("{devices: 3, batch: 8}", "batch (8) must divide among the devices (3)")] {
        let recipe = dir.path().join("r.yaml");
        let setting = setting.trim_start_matches('{').trim_end_matches('}');
        std::fs::write(&recipe, format!("name: r\npasses: [{LOSSLESS}, {{prune: {{ratio: 0.5, compensate: none}}}}, {{recover: {{{setting}}}}}, cleanup]\n")).unwrap();
        let out = dir.path().join("o");
        let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{setting}: {}", r.stderr);
        assert!(r.stderr.contains(needle) && r.stderr.trim().lines().count() == 1, "{setting}: {}", r.stderr);
        assert!(!out.join("model.onnx").exists(), "{setting}: nothing written");
    }
}

/// The same compile twice on one machine gives the same bytes, also when another process keeps
/// a core busy during the second: training runs for steps (not minutes) on a fixed thread
/// count with deterministic kernels. The shipped `detect-pruned-int8` (which runs
/// `detect-pruned-f32`'s passes, then INT8) with a short step budget, compiled and then rebuilt
/// from its manifest under load. (It compiled `detect-pruned-f32` twice as well, which added
/// nothing the rebuild does not cover and kept both cores busy for the other tests' minutes.)
#[test]
fn a_pruned_compile_is_byte_identical_when_repeated_under_load() {
    let dir = tempfile::tempdir().unwrap();
    // detect-pruned-int8 is `base: detect-pruned-f32` plus INT8: the edited copy beside it is
    // the base it reads.
    let text = std::fs::read_to_string(repo().join("passes/detect-pruned-f32.yaml")).unwrap();
    let shipped = "recover: {steps: 8000, lr: 3.0e-3, batch: 8, frames: 4096}";
    assert!(text.contains(shipped), "detect-pruned-f32's recover line moved; update this test");
    std::fs::write(dir.path().join("detect-pruned-f32.yaml"), text.replace(shipped, "recover: {steps: 30, lr: 3.0e-3, batch: 8, frames: 64}")).unwrap();
    let int8 = std::fs::read_to_string(repo().join("passes/detect-pruned-int8.yaml")).unwrap();
    assert!(int8.contains("base: detect-pruned-f32\n"), "detect-pruned-int8 no longer starts from detect-pruned-f32; update this test");
    let recipe = dir.path().join("detect-pruned-int8.yaml");
    std::fs::write(&recipe, int8).unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    let first = compile("models/trained/pdinet_v5_tiny_trained.onnx", recipe.to_str().unwrap(), &a);
    assert!(first["not_reproducible"].as_array().unwrap().is_empty(), "{}", first["not_reproducible"]);
    let passes: Vec<&str> = first["passes"].as_array().unwrap().iter().map(|p| p["pass"].as_str().unwrap()).collect();
    assert!(["prune", "recover", "quantize"].iter().all(|p| passes.contains(p)), "{passes:?}");
    let recover = first["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "recover").unwrap()["details"].clone();
    // The trained weights are in the model (the held-out rule kept them): the bytes compared
    // below are the training's.
    assert_eq!(recover["kept"], true, "{recover}");
    let training = recover["training"].clone();
    assert_eq!((training["steps"].as_u64(), training["steps_planned"].as_u64(), training["capped"].as_bool()), (Some(30), Some(30), Some(false)), "{training}");
    let manifest = std::fs::read_to_string(a.join("manifest.yaml")).unwrap();
    assert!(manifest.contains("reproducible: true") && manifest.contains("steps: 30"), "{manifest}");

    // One busy loop on the 2-core machines this runs on: the training shares the cores with it
    // (two loops also starved the test running beside this one). It spins only while this test
    // holds a workers' turn, which the rebuild then runs in without taking it again: queued
    // behind another test's training, it would slow that training instead. Without the lock's
    // variables the rebuild's share of the cores is all of them: under `scripts/test`, which
    // gives each turn one core, the bytes hold only if it trains on the count recorded.
    let turn = pdi_compile::pyenv::exclusive().unwrap();
    let load: Vec<std::process::Child> = (0..1).map(|_| std::process::Command::new("sh").args(["-c", "while :; do :; done"]).spawn().unwrap()).collect();
    // The manifest alone rebuilds it.
    let r = cli_without(&["rebuild", a.to_str().unwrap(), "-o", b.to_str().unwrap(), "--json"], &["PDI_WORKER_LOCK"]);
    for mut p in load {
        let _ = p.kill();
        let _ = p.wait();
    }
    drop(turn);
    assert_eq!(r.code, 0, "{}\n{}", r.stdout, r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert!(report["identical"] == true && report["compared_by"].as_str().unwrap().starts_with("bytes"), "{report}");
    let (x, y) = (std::fs::read(a.join("model.onnx")).unwrap(), std::fs::read(b.join("model.onnx")).unwrap());
    assert!(x == y, "the first compile and its rebuild differ ({} and {} bytes)", x.len(), y.len());

    // Its base compiled alone, then only its own passes on that model, give the same bytes:
    // scripts/results measures detect-pruned-f32 and detect-pruned-int8 from one training so.
    let (c, d) = (dir.path().join("c"), dir.path().join("d"));
    compile("models/trained/pdinet_v5_tiny_trained.onnx", dir.path().join("detect-pruned-f32.yaml").to_str().unwrap(), &c);
    let int8 = std::fs::read_to_string(&recipe).unwrap();
    let own = dir.path().join("own.yaml");
    std::fs::write(&own, format!("name: detect-pruned-int8\n{}", int8[int8.find("\npasses:").unwrap()..].trim_start())).unwrap();
    compile(c.join("model.onnx").to_str().unwrap(), own.to_str().unwrap(), &d);
    assert!(std::fs::read(d.join("model.onnx")).unwrap() == x, "detect-pruned-int8 in two stages differs from the recipe in one");
}

/// A time cap that stops training early is said on stderr, in the report and in the manifest,
/// which marks the artifact as not reproducible.
#[test]
fn a_training_stopped_by_its_time_cap_is_marked_not_reproducible() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("capped.yaml");
    let prune = "{prune: {ratio: 0.5}}";
    std::fs::write(&recipe, format!("name: capped\npasses: [{LOSSLESS}, {prune}, {{recover: {{steps: 100000, minutes: 0.05, frames: 32, batch: 8}}}}, cleanup]\n")).unwrap();
    let out = dir.path().join("out");
    let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stderr.contains("of 100000 steps by the time cap"), "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert!(report["not_reproducible"][0].as_str().unwrap().contains("by the time cap"), "{}", report["not_reproducible"]);
    let manifest = std::fs::read_to_string(out.join("manifest.yaml")).unwrap();
    assert!(manifest.contains("reproducible: false") && manifest.contains("by the time cap"), "{manifest}");
}

/// Recovery as one torch.distributed job of 2 gloo ranks (torchrun, DDP), each with half of
/// every batch of 8, against one process with the whole batches: the same frames, frame order
/// and augmentation, the loss normalized over the whole batch. The weights differ by float
/// summation order only (the ranks' gradients are averaged by an all-reduce, and each rank
/// runs 1 thread where the process runs 2), and the held-out rule keeps both.
#[test]
fn two_gloo_ranks_train_the_weights_of_one_process() {
    let dir = tempfile::tempdir().unwrap();
    let model = "models/trained/pdinet_v5_tiny_trained.onnx";
    let mut trained = Vec::new();
    for devices in [1, 2] {
        let recipe = dir.path().join(format!("r{devices}.yaml"));
        std::fs::write(&recipe, format!("name: r\npasses: [{LOSSLESS}, {{prune: {{ratio: 0.5, compensate: none}}}}, {{recover: {{steps: 12, frames: 48, batch: 8, threads: 2, devices: {devices}}}}}, cleanup]\n")).unwrap();
        let out = dir.path().join(format!("d{devices}"));
        let report = compile(model, recipe.to_str().unwrap(), &out);
        let r = report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "recover").unwrap()["details"].clone();
        assert_eq!(r["training"]["ranks"], devices, "{r}");
        assert_eq!(r["training"]["steps"], 12, "{r}");
        assert_eq!(r["kept"], true, "the held-out rule keeps the training: {r}");
        trained.push((load(&out.join("model.onnx")), r));
    }
    let (one, two) = (&trained[0].0, &trained[1].0);
    let (g1, g2) = (one.graph.as_ref().unwrap(), two.graph.as_ref().unwrap());
    assert_eq!(g1.node, g2.node);
    let (mut diff, mut norm, mut worst) = (0f64, 0f64, 0f64);
    for (a, b) in g1.initializer.iter().zip(&g2.initializer) {
        assert_eq!(a.name, b.name);
        let (a, b) = (pdi_compile::onnx::tensor_proto::to_tensor(a).unwrap(), pdi_compile::onnx::tensor_proto::to_tensor(b).unwrap());
        let (Some(a), Some(b)) = (a.as_f32(), b.as_f32()) else { continue };
        for (x, y) in a.iter().zip(b) {
            diff += ((x - y) as f64).powi(2);
            norm += (*x as f64).powi(2);
            worst = worst.max((x - y).abs() as f64);
        }
    }
    let rel = (diff / norm).sqrt();
    let losses: Vec<f64> = trained.iter().map(|(_, r)| r["training"]["held_out_loss_after"].as_f64().unwrap()).collect();
    println!("weights rel L2 {rel:.2e}, worst {worst:.2e}; held-out loss after: {losses:?}");
    // 12 Adam steps at lr 1e-3 move a weight by up to ~1.2e-2; summation-order noise stays
    // orders of magnitude below (a sign flip of a near-zero gradient moves one weight by at
    // most 2 lr per step, which the whole-model rel L2 does not feel).
    assert!(rel < 1e-6, "weights rel L2 {rel:e} between 1 and 2 ranks (measured 7e-9)");
    assert!((losses[0] - losses[1]).abs() <= 1e-4 * losses[0], "held-out losses {losses:?}");
}

/// The full-size v5 (width 1.0, 640x480, random weights: what the paper deploys) through
/// pruning and a short recovery on the CPU, end to end: the export, the lossless passes, a
/// structured cut, 2 training steps of batch 2 (one whole frame a step: `crop: auto` counts
/// the batch in frames of 256x192), the held-out rule. Its training frames stay
/// within the 2 GiB the pass holds in memory, and the report gives the frame rate.
#[test]
fn the_full_size_model_recovers_end_to_end_on_the_cpu() {
    let dir = tempfile::tempdir().unwrap();
    let export = dir.path().join("full");
    export_pdinet(&["--out", export.to_str().unwrap(), "--width", "1.0", "--size", "640x480", "--head", "v5", "--psf", "input", "--opset", "17", "--fold", "off"]);
    let model = std::fs::read_dir(&export).unwrap().map(|e| e.unwrap().path()).find(|p| p.extension().is_some_and(|e| e == "onnx")).expect("an exported model");
    assert!(std::fs::metadata(&model).unwrap().len() > 50 << 20, "the full-size export");
    let recipe = dir.path().join("full.yaml");
    std::fs::write(&recipe, "name: full\nbase: detect-lossless\npasses:\n  - prune: {ratio: 0.5, compensate: none}\n  - recover: {steps: 2, batch: 2, frames: 8}\n  - cleanup\n").unwrap();
    let report = compile(model.to_str().unwrap(), recipe.to_str().unwrap(), &dir.path().join("out"));
    let r = &report["passes"].as_array().unwrap().iter().find(|p| p["pass"] == "recover").unwrap()["details"];
    println!("{}", serde_json::to_string_pretty(&r["training"]).unwrap());
    assert_eq!(r["training"]["steps"], 2, "{r}");
    assert!(r["training"]["crop"].is_null(), "640x480 frames train whole: {r}");
    assert_eq!(r["training"]["batch"], 1, "2 frames of 256x192 make one of 640x480: {r}");
    assert!(r["training"]["frames_per_second"].as_f64().unwrap() > 0.0, "{r}");
    let frames = r["frames"].as_u64().unwrap();
    // 8 asked for plus the draw that holds out a quarter for the rule: all in memory, far
    // under the pass's 2 GiB of pixels (which caps a larger ask, with a warning).
    assert!(frames >= 8 && frames * 640 * 480 * 4 <= 2 << 30, "{frames} training frames held");
    // The held-out rule's decision follows from what it reports: kept exactly when the
    // detections agree better with the unpruned model's, or on a tie when the worst output
    // group got closer (two steps may go either way).
    let worst = |m: &serde_json::Value| m.as_object().unwrap().iter().filter(|(k, _)| k.contains('/')).map(|(_, v)| v.as_f64().unwrap()).fold(0.0, f64::max);
    let (before, after) = (worst(&r["output_rel_l2"]["before"]), worst(&r["output_rel_l2"]["after"]));
    assert!(before.is_finite() && after.is_finite() && before > 0.0, "{r}");
    let agreement = |k: &str| r["detection_agreement"][k].as_f64().unwrap_or_else(|| panic!("a decodable head is judged by its detections: {r}"));
    let (a0, a1) = (agreement("before"), agreement("after"));
    let kept = if a1 != a0 { a1 > a0 } else { after < before };
    assert_eq!(r["kept"], kept, "kept must follow the agreement ({a0} -> {a1}), then the worst group ({before} -> {after}): {r}");
    let macs = |k: &str| report[k]["macs"].as_f64().unwrap();
    assert!(macs("after") < 0.5 * macs("before"), "pruned: {} of {} MACs", macs("after"), macs("before"));
}

/// A training set holds what fits in 2 GiB of f32 pixels at the image input's size: an ask
/// that fits passes whole, a larger one trains on what fits (10922 frames at 256x192, 1747 at
/// 640x480).
#[test]
fn a_training_set_holds_two_gib_of_pixels() {
    use pdi_compile::calib_frames::affordable_frames;
    use pdi_compile::ir::{infer, Graph};
    for (model, fit) in [("pdinet_v5_w0.25_trained.onnx", 10922), ("pdinet_v5_w0.25_640x480_trained.onnx", 1747)] {
        let m = load(&repo().join("models/trained").join(model));
        let g = Graph::build(m.graph.as_ref().unwrap()).unwrap();
        let inf = infer(&g);
        assert_eq!(affordable_frames("recover", &g, &inf, fit), fit, "{model}");
        assert_eq!(affordable_frames("recover", &g, &inf, fit + 1), fit, "{model}");
    }
}

/// Training on crops of 640x480 frames: the plan cuts exactly the three folded PSF gate maps
/// (one value per cell of the stride-4 grid) with each window, on the coarsest head grid;
/// whole frames with `crop: auto` or `none`; `crop_context.py` cuts them the same way. A model that fixes a shape from the frame's
/// size where the training reads (a Reshape before a head) is refused in one line, and so
/// are crop sizes off the grid (when the recipe loads) or larger than the frames.
#[test]
fn crops_cut_the_gate_maps_and_refuse_what_cannot_follow() {
    use pdi_compile::torch::crops::{plan, Crop};
    use pdi_compile::torch::heads::{feature_specs, head_specs};
    let dir = tempfile::tempdir().unwrap();
    let export = dir.path().join("e");
    export_pdinet(&["--out", export.to_str().unwrap(), "--weights-from", "models/trained/pdinet_v5_tiny_trained.onnx", "--size", "640x480"]);
    let compiled = dir.path().join("c");
    compile(export.join("pdinet_v5_tiny_trained_640x480.onnx").to_str().unwrap(), "passes/detect-lossless.yaml", &compiled);
    let m = load(&compiled.join("model.onnx"));
    let values: Vec<String> = head_specs(&m).unwrap().iter().chain(feature_specs(&m, &Default::default()).unwrap().iter()).map(|s| s["value"].as_str().unwrap().to_string()).collect();
    let p = plan(Crop::Size(256, 192), (&m, &values), (&m, &values), (480, 640)).unwrap().expect("640x480 frames are cropped");
    assert_eq!((p.h, p.w, p.step), (192, 256, 32));
    assert_eq!(p.student.len(), 3, "{:?}", p.student);
    assert!(p.student.values().all(|&s| s == 4) && p.student == p.teacher, "{p:?}");
    assert!(plan(Crop::Off, (&m, &values), (&m, &values), (480, 640)).unwrap().is_none());
    assert!(plan(Crop::Auto, (&m, &values), (&m, &values), (480, 640)).unwrap().is_none());
    assert_eq!(plan(Crop::Size(320, 256), (&m, &values), (&m, &values), (480, 640)).unwrap().map(|p| (p.h, p.w)), Some((256, 320)));

    // `crop_context.py`, through the trainer's ONNX Runtime teacher, cuts the gate maps as
    // the plan does: a window that is the whole frame scores what the frame scores, to float
    // noise; a 256x192 one does not (the tiny v5's heads read beyond a crop's edges), while a
    // gated value with little context beyond its gate map agrees inside it (a gate map cut at
    // the wrong offset would not).
    let data = dir.path().join("frames");
    std::fs::create_dir(&data).unwrap();
    for k in 0..2u32 {
        let px: Vec<u16> = (0..640 * 480u32).map(|i| ((i % 640 + i / 640 * 3 + k * 977) % 4096 * 11) as u16).collect();
        image::ImageBuffer::<image::Luma<u16>, _>::from_raw(640, 480, px).unwrap().save(data.join(format!("f{k}.png"))).unwrap();
    }
    let context = |value: &str, crop: &str, margin: &str| -> f64 {
        let out = std::process::Command::new(pdi_compile::pyenv::torch_python().unwrap()).current_dir(repo())
            .args(["src/torch/crop_context.py", "--model", compiled.join("model.onnx").to_str().unwrap(), "--data", data.to_str().unwrap(),
                   "--value", value, "--crop", crop, "--windows", "3", "--margin", margin]).output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let r: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        r["rel_l2"][value].as_f64().unwrap()
    };
    let (whole, cropped) = (context(&values[0], "640x480", "0"), context(&values[0], "256x192", "0"));
    assert!(whole < 1e-5, "the whole frame as a window: rel L2 {whole}");
    assert!(cropped > 1e-3 && cropped.is_finite(), "a 256x192 window: rel L2 {cropped}");
    let gated = context("/bridge/Mul_4_output_0", "256x192", "16");
    assert!(gated < 1e-4, "a gated value 16 cells in from a window's edges: rel L2 {gated}");

    // A Reshape to the value's own shape after the first convolution: same values, but a
    // shape fixed from 640x480.
    let mut edited = m.clone();
    let g = edited.graph.as_mut().unwrap();
    let first = g.node.iter().position(|n| n.op_type == "Conv").unwrap();
    let value = g.node[first].output[0].clone();
    let graph = pdi_compile::ir::Graph::build(m.graph.as_ref().unwrap()).unwrap();
    let shape: Vec<i64> = pdi_compile::ir::infer(&graph).shape(&value).unwrap().iter().map(|&d| d as i64).collect();
    g.node[first].output[0] = format!("{value}_pre");
    g.initializer.push(pdi_compile::onnx::tensor_proto::from_tensor("fixed_shape", &Tensor::new(vec![4], pdi_compile::tensor::TensorData::I64(shape))));
    let reshape = pdi_compile::onnx::proto::NodeProto { name: "fixed".into(), op_type: "Reshape".into(), input: vec![format!("{value}_pre"), "fixed_shape".into()], output: vec![value], ..Default::default() };
    g.node.insert(first + 1, reshape);
    let err = plan(Crop::Size(256, 192), (&edited, &values), (&m, &values), (480, 640)).unwrap_err().to_string();
    assert!(err.contains("cannot train on crops: node 'fixed' (Reshape) fixes its output's shape") && !err.contains('\n'), "{err}");

    for (setting, needle) in [("crop: 250x192", "both sides must be positive multiples of 32"), ("crop: 320x256", "crop 320x256 is larger than the 256x192 frames")] {
        let recipe = dir.path().join("r.yaml");
        std::fs::write(&recipe, format!("name: r\npasses: [{LOSSLESS}, {{prune: {{ratio: 0.5, compensate: none}}}}, {{recover: {{steps: 2, batch: 2, frames: 8, {setting}}}}}, cleanup]\n")).unwrap();
        let out = dir.path().join("o");
        let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{setting}: {}", r.stderr);
        assert!(r.stderr.contains(needle) && r.stderr.trim().lines().count() == 1, "{setting}: {}", r.stderr);
        assert!(!out.join("model.onnx").exists(), "{setting}: nothing written");
    }
}
