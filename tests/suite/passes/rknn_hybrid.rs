//! `rknn-hybrid`: the layers it keeps in FP16 reach RKNN-Toolkit2's hybrid quantization.

use crate::common::*;
use crate::target_rknn::{compile, detect_rknn_then};

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
