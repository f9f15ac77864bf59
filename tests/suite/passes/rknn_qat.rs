//! `rknn-qat`: training on the toolkit's own quantization plan, and what reaches the NPU.

use crate::common::*;
use crate::target_rknn::{compile, detect_rknn_then};

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
