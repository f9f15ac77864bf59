//! `compile --target tract`: the folder proves tract loads and runs the model with fixed
//! shapes and matches ONNX Runtime; an NNEF archive is kept only when it loads faster.

use crate::common;
use crate::common::*;

#[test]
fn tract_target_writes_a_checked_folder() {
    let dir = tempfile::tempdir().unwrap();
    for model in ["models/trained/pdinet_v5_tiny_trained.onnx", "models/fixtures/pdinet_v8_input_op17_nofold.onnx"] {
        let out = dir.path().join(std::path::Path::new(model).file_stem().unwrap());
        let r = cli(&["compile", model, "--pipeline", "passes/detect-f32.yaml", "--psf", "calib/single_lwir_blur.npy", "--target", "tract", "-o", out.to_str().unwrap(), "--json"]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
        let check = &report["target_check"];
        println!("{model}: {check}");
        assert!(check["rel_l2_vs_ort"].as_f64().unwrap() <= 1e-4, "{check}");
        let load = check["load"].as_str().unwrap();
        assert!(out.join(load).is_file(), "{load} is in the folder");
        assert_eq!(out.join("model.nnef.tar").is_file(), load == "model.nnef.tar", "{}", check["nnef"]);
        let tract_yaml = std::fs::read_to_string(out.join("tract.yaml")).unwrap();
        assert!(tract_yaml.contains("onnx_load_ms") && tract_yaml.contains("shape"));
        // The bridge's 15x15 depthwise convolution ships in bands tract's SIMD kernel takes.
        assert!(tract_yaml.contains("depthwise_split") && tract_yaml.contains("/bridge/dw/Conv"), "{tract_yaml}");
        let shipped = common::load(&out.join("model.onnx"));
        assert!(!pdi_compile::ir::rewrite::split_depthwise::any_to_split(shipped.graph.as_ref().unwrap()));
        // Each convolution tract would run directly (the encoder's, at 256 columns and more)
        // was timed whole and tiled, and ships tiled exactly where the tiles were faster.
        let yaml: serde_json::Value = yaml_serde::from_str(&tract_yaml).unwrap();
        let forms = yaml["conv_tiles"].as_array().unwrap_or_else(|| panic!("no conv_tiles in {tract_yaml}"));
        assert!(forms.iter().any(|f| f["node"].as_str().unwrap().starts_with("/enc1/")), "{tract_yaml}");
        // One thread weighed against all of them; the advice follows the two medians.
        let threads = yaml["threads"].as_u64().unwrap();
        let fastest = yaml["fastest_threads"].as_u64().unwrap();
        if threads > 1 {
            let (one, all) = (yaml["one_thread_ms"].as_f64().unwrap(), yaml["all_threads_ms"].as_f64().unwrap());
            assert_eq!(fastest == 1, one < all * 0.95, "{tract_yaml}");
            assert!(fastest == 1 || fastest == threads, "{tract_yaml}");
        } else {
            assert_eq!(fastest, 1, "{tract_yaml}");
        }
        for f in forms {
            let (whole, tiled) = (f["whole_ms"].as_f64().unwrap(), f["tiled_ms"].as_f64().unwrap());
            let chosen = f["tiled"].as_bool().unwrap();
            assert!(whole > 0.0 && tiled > 0.0 && (!chosen || tiled < whole * 0.95), "{f}");
            let concat = format!("{}_tiles", f["node"].as_str().unwrap());
            assert_eq!(shipped.graph.as_ref().unwrap().node.iter().any(|n| n.name == concat), chosen, "{f}");
        }
        assert!(std::fs::read_to_string(out.join("manifest.yaml")).unwrap().contains("target: tract"));

        // A rebuild from the manifest reuses the timed choices (tiles, NNEF) instead of
        // timing again, and gives the same bytes on this machine.
        let again = dir.path().join(format!("{}-rebuilt", out.file_name().unwrap().to_str().unwrap()));
        let r = cli(&["rebuild", out.to_str().unwrap(), "-o", again.to_str().unwrap(), "--json"]);
        assert_eq!(r.code, 0, "{}\n{}", r.stdout, r.stderr);
        let rebuilt: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
        assert_eq!(rebuilt["identical"], true, "{rebuilt}");
        assert!(rebuilt["compared_by"].as_str().unwrap().starts_with("bytes"), "{rebuilt}");
        assert_eq!(std::fs::read(out.join("model.onnx")).unwrap(), std::fs::read(again.join("model.onnx")).unwrap());
        assert_eq!(out.join("model.nnef.tar").is_file(), again.join("model.nnef.tar").is_file(), "the NNEF choice is reused");
    }
}

/// A rebuild refuses, in one line, an input that changed since the build.
#[test]
fn a_rebuild_refuses_a_changed_input() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("model.onnx");
    std::fs::copy(repo().join("models/fixtures/pdinet_v8_input_op17_nofold.onnx"), &model).unwrap();
    let out = dir.path().join("out");
    let r = cli(&["compile", model.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let mut bytes = std::fs::read(&model).unwrap();
    bytes.extend_from_slice(b"\0");
    std::fs::write(&model, bytes).unwrap();
    let again = dir.path().join("again");
    let r = cli(&["rebuild", out.to_str().unwrap(), "-o", again.to_str().unwrap()]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("changed since") && r.stderr.trim().lines().count() == 1, "{}", r.stderr);
    assert!(!again.exists());
}

#[test]
fn tract_target_refuses_an_unbound_blur_map_input() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("cut");
    let r = cli(&["compile", "models/fixtures/pdinet_v5_input_op17_nofold.onnx", "--pipeline", "passes/detect-cut.yaml", "--target", "tract", "-o", out.to_str().unwrap()]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("one image input") && r.stderr.lines().count() == 1, "{}", r.stderr);
    assert!(!out.join("model.onnx").exists(), "no half-written folder");
}

/// An INT8 model is kept for tract only where tract ran it faster than the float model it was
/// quantized from; either way tract.yaml says which with both timings, and the shipped model
/// is the one it names.
#[test]
fn tract_target_weighs_int8_against_its_float_model() {
    let dir = tempfile::tempdir().unwrap();
    let recipe = dir.path().join("int8.yaml");
    std::fs::write(&recipe, recipe_edit("passes/detect-int8.yaml", "calib_frames: 64", "calib_frames: 6, analysis_frames: 2, held_out_frames: 2")).unwrap();
    let out = dir.path().join("int8");
    let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "--target", "tract", "--threads", "2", "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let check = &report["target_check"];
    assert_eq!(check["threads"], 2, "{check}");
    let why = check["int8"].as_str().unwrap_or_else(|| panic!("tract.yaml says what it did with INT8: {check}"));
    let shipped = load(&out.join("model.onnx"));
    let quantized = shipped.graph.as_ref().unwrap().node.iter().any(|n| n.op_type == "QuantizeLinear" || n.op_type == "QLinearConv");
    // The decision follows the two timings it reports.
    let ms: Vec<f64> = why.split(" ms").filter_map(|s| s.rsplit(' ').next()?.parse().ok()).collect();
    let [int8_ms, float_ms] = ms[..] else { panic!("two timings in: {why}") };
    assert_eq!(why.starts_with("kept"), int8_ms < float_ms, "{why}");
    if why.starts_with("kept") {
        assert!(quantized, "{why}");
    } else {
        assert!(why.starts_with("replaced by its float model") && !quantized, "{why}");
        assert!(r.stderr.contains("tract target: replaced"), "a warning says so: {}", r.stderr);
    }
    assert!(why.contains(" ms") && why.contains("float model"), "{why}");
}
