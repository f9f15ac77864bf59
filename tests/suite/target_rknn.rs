//! The RKNN target: `rknn-legalize` ends the graph at the head convolutions without
//! changing what the detector computes, the split-head post-processing in Rust decodes it
//! exactly like the original in-graph decode, `--target rknn` writes what the toolkit needs,
//! and `rknn-convert` builds it with RKNN-Toolkit2 2.5.0 and checks its simulator.

use crate::common::*;
use pdi_compile::analysis::head::HeadKind;
use pdi_compile::detect::decode::candidates;
use pdi_compile::detect::nms::nms;
use pdi_compile::detect::split_head::{decode_dense, detect, HeadLayout};
use pdi_compile::runtime::{ort_runtime::OrtRuntime, Runtime};
use std::collections::HashMap;

fn compile(model: &str, pipeline: &str, out: &std::path::Path, extra: &[&str]) -> CliResult {
    let mut args = vec!["compile", model, "--pipeline", pipeline, "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()];
    args.extend(extra);
    cli(&args)
}

/// Same frame through the original (in-graph decode) and the legalized model: the Rust
/// decode of the split outputs equals the original's decoded tensor, and the deployment
/// path (score skipping + NMS) equals NMS over the original's candidates.
#[test]
fn split_head_post_processing_equals_the_in_graph_decode() {
    let dir = tempfile::tempdir().unwrap();
    for (model, kind) in [("models/trained/pdinet_v5_tiny_trained.onnx", HeadKind::Yolov5Anchor), ("models/fixtures/pdinet_v8_input_op17_nofold.onnx", HeadKind::Yolov8Dfl)] {
        let (orig_dir, legal_dir) = (dir.path().join("orig"), dir.path().join("legal"));
        assert_eq!(compile(model, "passes/detect-f32.yaml", &orig_dir, &[]).code, 0);
        let r = compile(model, "passes/detect-rknn.yaml", &legal_dir, &[]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let (orig, legal) = (load(&orig_dir.join("model.onnx")), load(&legal_dir.join("model.onnx")));
        let layout = HeadLayout::from_model(&legal).unwrap();
        assert_eq!(layout.kind, kind);
        assert!(legal.ir_version <= 9);
        let g = legal.graph.as_ref().unwrap();
        let outputs: Vec<&str> = g.output.iter().map(|o| o.name.as_str()).collect();
        assert_eq!(outputs, layout.output_names().iter().map(String::as_str).collect::<Vec<_>>());
        for o in &g.output {
            let producer = g.node.iter().find(|n| n.output.contains(&o.name)).unwrap();
            assert!(["Conv", "Sigmoid", "Clip"].contains(&producer.op_type.as_str()), "{} ends in {}", o.name, producer.op_type);
        }
        assert!(!g.node.iter().any(|n| ["Reshape", "Transpose", "Softmax", "Pow"].contains(&n.op_type.as_str())), "no decode left");

        let feeds = inputs_for(&orig, 3);
        let original = OrtRuntime::new(&orig).unwrap().run(&feeds).unwrap().remove(0).1;
        let split: HashMap<_, _> = OrtRuntime::new(&legal).unwrap().run(&feeds).unwrap().into_iter().collect();
        let dense = decode_dense(&layout, &split).unwrap();
        assert_eq!(dense.shape, original.shape);
        let worst = original.as_f32().unwrap().iter().zip(dense.as_f32().unwrap()).map(|(a, b)| (a - b).abs() / a.abs().max(1.0)).fold(0f32, f32::max);
        println!("{model}: split decode vs in-graph decode, worst relative difference {worst:.2e}");
        assert!(worst <= 1e-4, "{worst}");

        let conf = if kind == HeadKind::Yolov5Anchor { 0.25 } else { 0.02 };
        let expected = nms(candidates(kind, &original, conf).unwrap(), 0.45, 300);
        let (got, skipped) = detect(&layout, &split, conf, 0.45, 300).unwrap();
        assert!(!expected.is_empty(), "{model}: the frame has detections to compare");
        assert_eq!(got.len(), expected.len(), "{model}");
        for (a, b) in got.iter().zip(&expected) {
            assert_eq!(a.class, b.class);
            assert!((a.score - b.score).abs() <= 1e-4 && a.bbox.iter().zip(&b.bbox).all(|(x, y)| (x - y).abs() <= 1e-2), "{a:?} vs {b:?}");
        }
        println!("  {} detections; {} of {} cells skipped before decoding", got.len(), skipped.skipped, skipped.cells);
        assert!(skipped.skipped > 0);
    }
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
fn detect_rknn_then(dir: &std::path::Path, pass: &str) -> std::path::PathBuf {
    let recipe = dir.join("detect-rknn-then.yaml");
    std::fs::write(&recipe, format!("name: detect-rknn-then\nbase: detect-rknn\npasses:\n  - {pass}\n")).unwrap();
    recipe
}

/// rknn-hybrid's FP16 layers (two pinned by `fp16`, any the search adds) travel through
/// rknn.yaml to the toolkit's hybrid quantization: the build log shows the float16 spans,
/// the simulator still agrees with ORT, and a span the toolkit skips (its fusion renamed the
/// bridge convolution's input) is counted out and warned about.
#[test]
fn rknn_hybrid_layers_reach_the_toolkit() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = detect_rknn_then(dir.path(), "rknn-hybrid: {error_budget: 0.02, max_layers: 4, fp16: [/enc2/body/body.3/Conv, /bridge/Conv]}");
    let out = dir.path().join("rknn");
    let r = compile("models/trained/pdinet_v5_tiny_trained.onnx", recipe.to_str().unwrap(), &out, &["--target", "rknn"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let hybrid = &report["passes"].as_array().unwrap().last().unwrap()["details"];
    assert!(hybrid["simulated_int8_worst_rel_l2"].as_f64().unwrap() > 0.02 && !hybrid["tried_and_rejected"].as_array().unwrap().is_empty(), "the search ran past its budget: {hybrid}");
    let config: serde_json::Value = yaml_serde::from_str(&std::fs::read_to_string(out.join("rknn.yaml")).unwrap()).unwrap();
    let layers = config["quantization"]["fp16_layers"].as_array().unwrap();
    assert_eq!((layers[0]["node"].as_str(), layers[1]["node"].as_str()), (Some("/enc2/body/body.3/Conv"), Some("/bridge/Conv")), "the pinned layers come first: {layers:?}");
    let model = load(&out.join("model.onnx"));
    for l in layers {
        let node = model.graph.as_ref().unwrap().node.iter().find(|n| n.name == l["node"].as_str().unwrap()).unwrap();
        assert_eq!((node.input[0].as_str(), node.output[0].as_str()), (l["input"].as_str().unwrap(), l["output"].as_str().unwrap()));
    }
    let r = cli(&["rknn-convert", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}\n{}", r.stdout, r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    assert_eq!(report["fp16_layers"].as_array().unwrap().len(), layers.len());
    let built = report["fp16_layers_built"].as_u64().unwrap() as usize;
    assert!(built >= 1 && built < layers.len(), "{built} of {} spans built", layers.len());
    assert!(r.stderr.contains("FP16 spans rknn.yaml asks for"), "{}", r.stderr);
    let log = std::fs::read_to_string(out.join("rknn_build.log")).unwrap();
    assert!(log.contains("dtype: float16"), "the toolkit built float16 spans");
    assert!(!out.join("model.quantization.cfg").exists(), "hybrid intermediates stay out of the artifact");
}

/// rknn-qat trains on RKNN-Toolkit2's own quantization plan, and the NPU gets what was
/// trained: the graph is unchanged and only convolution weights and biases move; every trained
/// weight channel lies on the toolkit's per-channel grid with both ends occupied (so the
/// toolkit's requantization finds the trained integers); the trained ranges reach rknn.yaml
/// and the toolkit's config; the simulator passes the cosine gate against the float model the
/// training started from, with nothing on the CPU.
#[test]
fn rknn_qat_trains_on_the_toolkits_plan_and_reaches_the_npu() {
    let dir = tempfile::tempdir().unwrap();
    let plain = dir.path().join("plain");
    let r = compile("models/trained/pdinet_v5_tiny_trained.onnx", "passes/detect-rknn.yaml", &plain, &["--target", "rknn"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let recipe = detect_rknn_then(dir.path(), "rknn-qat: {steps: 16, lr: 0.0005, frames: 32}");
    let out = dir.path().join("qat");
    let r = compile("models/trained/pdinet_v5_tiny_trained.onnx", recipe.to_str().unwrap(), &out, &["--target", "rknn"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(out.join("report.json")).unwrap()).unwrap();
    let qat = &report["passes"].as_array().unwrap().last().unwrap()["details"];
    println!("{qat:#}");
    assert_eq!(qat["kept"], true, "training brought the worst output closer to float");
    assert!(qat["trained_points"].as_u64().unwrap() > 100);
    let left = qat["left_to_the_toolkit"].as_object().unwrap();
    assert!(left.values().any(|why| why.as_str().unwrap().starts_with("Conv+SiLU")), "fused Conv+SiLU outputs are not rounded");

    let (before, after) = (load(&plain.join("model.onnx")), load(&out.join("model.onnx")));
    let (gb, ga) = (before.graph.as_ref().unwrap(), after.graph.as_ref().unwrap());
    assert_eq!(gb.node, ga.node, "the graph is unchanged");
    let conv_params: std::collections::HashSet<&str> = ga.node.iter().filter(|n| n.op_type == "Conv").flat_map(|n| n.input[1..].iter().map(String::as_str)).collect();
    let mut changed = 0;
    for (a, b) in ga.initializer.iter().zip(&gb.initializer) {
        assert_eq!(a.name, b.name);
        if a != b {
            assert!(conv_params.contains(a.name.as_str()), "only convolution weights and biases move: {}", a.name);
            changed += 1;
        }
    }
    assert!(changed > 10, "{changed} parameters changed");
    // On the toolkit's grid: each channel's min and max on its ends, every weight on a step.
    // (Convolutions the toolkit splits per concatenated input have a grid per part.)
    let concat_outputs: std::collections::HashSet<&str> = ga.node.iter().filter(|n| n.op_type == "Concat").map(|n| n.output[0].as_str()).collect();
    let mut checked = 0;
    for n in ga.node.iter().filter(|n| n.op_type == "Conv" && !concat_outputs.contains(n.input[0].as_str())) {
        let w = pdi_compile::onnx::tensor_proto::to_tensor(ga.initializer.iter().find(|t| t.name == n.input[1]).unwrap()).unwrap();
        let values = w.as_f32().unwrap();
        let (q, scales, zps) = pdi_compile::quant::at_points::asymmetric_weights(values, w.shape[0]);
        let per = values.len() / w.shape[0];
        for (k, &v) in values.iter().enumerate() {
            let c = k / per;
            let back = (q[k] as f64 - zps[c] as f64) * scales[c];
            assert!((v as f64 - back).abs() <= 1e-3 * scales[c], "{}: weight {k} is off the grid ({v} vs {back})", n.name);
        }
        checked += 1;
    }
    assert!(checked > 50, "{checked} convolutions checked");

    let config: serde_json::Value = yaml_serde::from_str(&std::fs::read_to_string(out.join("rknn.yaml")).unwrap()).unwrap();
    let points = config["quantization"]["trained_points"].as_object().unwrap();
    assert_eq!((points["image_int8"]["min"].as_f64(), points["image_int8"]["max"].as_f64()), (Some(0.0), Some(1.0)), "the image keeps the 8-bit pixel grid");
    let r = cli(&["rknn-convert", out.to_str().unwrap(), "--reference", plain.join("model.onnx").to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}\n{}", r.stdout, r.stderr);
    let convert: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    println!("{convert:#}");
    assert!(convert["quantization"].as_str().unwrap().starts_with("rknn-qat's trained points"), "{}", convert["quantization"]);
    assert_eq!(convert["cpu_layers"].as_array().unwrap().len(), 0);
    for a in convert["outputs"].as_array().unwrap().iter().chain(convert["groups"].as_array().unwrap()) {
        assert!(a["cosine"].as_f64().unwrap() >= 0.99, "{a}");
    }
    // The emulation is close to the toolkit's arithmetic, not equal to it (measured on this
    // model: cosine 0.991–0.9999 per output after training).
    let emulated = convert["trained_qdq"].as_array().unwrap();
    assert_eq!(emulated.len(), 6, "every output compared with the trained QDQ model");
    for a in emulated {
        assert!(a["cosine"].as_f64().unwrap() >= 0.98, "{a}");
    }
}
