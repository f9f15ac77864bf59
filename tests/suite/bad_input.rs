//! Malformed files: one clear line on stderr, exit code 2, no panic, no partial output.

use crate::common::*;
use pdi_compile::onnx::proto::*;
use prost::Message;
use std::path::Path;

fn f32_input(name: &str, dims: &[i64]) -> ValueInfoProto {
    let dim = dims.iter().map(|&d| Dimension { value: Some(DimensionValue::DimValue(d)), denotation: String::new() }).collect();
    ValueInfoProto {
        name: name.into(),
        r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: 1, shape: Some(TensorShapeProto { dim }) })), denotation: String::new() }),
        ..Default::default()
    }
}

fn node(op: &str, inputs: &[&str], outputs: &[&str]) -> NodeProto {
    NodeProto { op_type: op.into(), name: format!("{op}_{}", outputs[0]), input: inputs.iter().map(|s| s.to_string()).collect(), output: outputs.iter().map(|s| s.to_string()).collect(), ..Default::default() }
}

fn model(nodes: Vec<NodeProto>, inputs: Vec<ValueInfoProto>, outputs: &[&str], inits: Vec<TensorProto>) -> ModelProto {
    ModelProto {
        ir_version: 8,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
        graph: Some(GraphProto {
            node: nodes,
            input: inputs,
            output: outputs.iter().map(|o| ValueInfoProto { name: o.to_string(), ..Default::default() }).collect(),
            initializer: inits,
            ..Default::default()
        }),
        ..Default::default()
    }
}

fn expect_clean_error(file: &Path, needle: &str) {
    let out_dir = file.with_extension("out");
    let f = file.to_str().unwrap();
    for args in [vec!["inspect", f], vec!["compile", f, "--pipeline", "passes/identity.yaml", "-o", out_dir.to_str().unwrap()], vec!["verify", "--reference", f, "--candidate", f, "--random", "1", "--runs", "0"]] {
        let r = cli(&args);
        assert_eq!(r.code, 2, "{args:?}: exit {} stderr {}", r.code, r.stderr);
        let lines: Vec<&str> = r.stderr.lines().collect();
        assert_eq!(lines.len(), 1, "{args:?}: expected one line, got {:?}", r.stderr);
        assert!(lines[0].starts_with("error: "), "{:?}", lines[0]);
        assert!(lines[0].to_lowercase().contains(needle), "{args:?}: {:?} does not mention {needle:?}", lines[0]);
        assert!(!r.stderr.contains("panicked") && !r.stderr.contains("internal error"));
        assert!(!out_dir.join("model.onnx").exists(), "a failed compile left an output");
    }
}

#[test]
fn malformed_models_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    let good = std::fs::read(repo().join("models/fixtures/pdinet_v5_const_op13_fold.onnx")).unwrap();
    expect_clean_error(&write("truncated.onnx", &good[..good.len() / 2]), "protobuf");
    expect_clean_error(&write("garbage.onnx", b"\xff\xff\xff\xff not onnx"), "protobuf");

    let x = || f32_input("x", &[1, 3, 8, 8]);
    let dangling = model(vec![node("Relu", &["nowhere"], &["y"])], vec![x()], &["y"], vec![]);
    expect_clean_error(&write("dangling.onnx", &dangling.encode_to_vec()), "dangling value name 'nowhere'");

    let cycle = model(vec![node("Add", &["x", "b"], &["a"]), node("Relu", &["a"], &["b"])], vec![x()], &["b"], vec![]);
    expect_clean_error(&write("cycle.onnx", &cycle.encode_to_vec()), "cycle");

    let negative = model(vec![node("Relu", &["x"], &["y"])], vec![f32_input("x", &[1, -3, 8, 8])], &["y"], vec![]);
    expect_clean_error(&write("negative.onnx", &negative.encode_to_vec()), "negative dimension");

    let absurd = model(vec![node("Relu", &["x"], &["y"])], vec![f32_input("x", &[1, 3, 1 << 40, 8])], &["y"], vec![]);
    expect_clean_error(&write("absurd.onnx", &absurd.encode_to_vec()), "absurd dimension");

    // Each dimension plausible, their product not: refused before a frame is allocated.
    let huge = model(vec![node("Relu", &["x"], &["y"])], vec![f32_input("x", &[1, 1, 1 << 30, 1 << 30])], &["y"], vec![]);
    expect_clean_error(&write("huge.onnx", &huge.encode_to_vec()), "elements");

    let lying = TensorProto { name: "w".into(), dims: vec![1 << 20, 1 << 20], data_type: 1, raw_data: vec![0; 16], ..Default::default() };
    let lies = model(vec![node("Add", &["x", "w"], &["y"])], vec![x()], &["y"], vec![lying]);
    expect_clean_error(&write("lying_initializer.onnx", &lies.encode_to_vec()), "initializer 'w'");

    for (name, loc) in [("escape_dotdot.onnx", "../secret.bin"), ("escape_abs.onnx", "/etc/passwd")] {
        let ext = TensorProto {
            name: "w".into(),
            dims: vec![4],
            data_type: 1,
            data_location: DATA_LOCATION_EXTERNAL,
            external_data: vec![StringStringEntryProto { key: "location".into(), value: loc.into() }],
            ..Default::default()
        };
        let m = model(vec![node("Add", &["x", "w"], &["y"])], vec![x()], &["y"], vec![ext]);
        expect_clean_error(&write(name, &m.encode_to_vec()), "external data path");
    }
    expect_clean_error(&dir.path().join("missing.onnx"), "cannot read");
}

#[test]
fn bad_pipelines_and_outputs_fail_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let fixture = repo().join("models/fixtures/pdinet_v5_const_op13_fold.onnx");
    let bad = dir.path().join("bad.yaml");
    std::fs::write(&bad, "name: x\npasses:\n  - no-such-pass\n").unwrap();
    let out = dir.path().join("o");
    let r = cli(&["compile", fixture.to_str().unwrap(), "--pipeline", bad.to_str().unwrap(), "-o", out.to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("unknown pass 'no-such-pass'"), "{}", r.stderr);
    assert!(!out.exists(), "nothing is written when the pipeline is bad");

    let file_as_dir = dir.path().join("taken");
    std::fs::write(&file_as_dir, "x").unwrap();
    let r = cli(&["compile", fixture.to_str().unwrap(), "--pipeline", "passes/identity.yaml", "-o", file_as_dir.to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.contains("is not a folder"), "{}", r.stderr);
}

/// Nonsense that is structurally valid must not crash shape inference: inspect answers
/// (possibly with unknown shapes), never with an internal error.
#[test]
fn hostile_shapes_do_not_crash_inspect() {
    let dir = tempfile::tempdir().unwrap();
    let ints = |name: &str, v: Vec<i64>| AttributeProto { name: name.into(), r#type: AttributeType::Ints as i32, ints: v, ..Default::default() };
    let int = |name: &str, v: i64| AttributeProto { name: name.into(), r#type: AttributeType::Int as i32, i: Some(v), ..Default::default() };
    let i64s = |name: &str, v: Vec<i64>| pdi_compile::onnx::tensor_proto::from_tensor(name, &pdi_compile::tensor::Tensor::new(vec![v.len()], pdi_compile::tensor::TensorData::I64(v)));
    let scalar = TensorProto { name: "s".into(), data_type: 1, raw_data: 1f32.to_le_bytes().to_vec(), ..Default::default() };
    let mut nodes = vec![
        NodeProto { op_type: "Concat".into(), input: vec!["s".into(), "s".into()], output: vec!["c".into()], attribute: vec![int("axis", 5)], ..Default::default() },
        NodeProto { op_type: "Conv".into(), input: vec!["x".into(), "w1".into()], output: vec!["v".into()], ..Default::default() },
        NodeProto { op_type: "DepthToSpace".into(), input: vec!["x".into()], output: vec!["d".into()], attribute: vec![int("blocksize", 0)], ..Default::default() },
        NodeProto { op_type: "Div".into(), input: vec!["min".into(), "neg".into()], output: vec!["q".into()], ..Default::default() },
        NodeProto { op_type: "Slice".into(), input: vec!["x".into(), "st".into(), "en".into(), "ax".into()], output: vec!["sl".into()], ..Default::default() },
        NodeProto { op_type: "Squeeze".into(), input: vec!["x".into(), "ax".into()], output: vec!["sq".into()], ..Default::default() },
        NodeProto { op_type: "MatMul".into(), input: vec!["s".into(), "s".into()], output: vec!["mm".into()], ..Default::default() },
        NodeProto { op_type: "ConvTranspose".into(), input: vec!["x".into(), "w4".into()], output: vec!["ct".into()], attribute: vec![ints("strides", vec![2])], ..Default::default() },
    ];
    for (i, n) in nodes.iter_mut().enumerate() {
        n.name = format!("n{i}");
    }
    let outputs: Vec<String> = nodes.iter().map(|n| n.output[0].clone()).collect();
    let m = ModelProto {
        ir_version: 8,
        opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }],
        graph: Some(GraphProto {
            node: nodes,
            input: vec![f32_input("x", &[1, 3, 8, 8])],
            output: outputs.iter().map(|o| ValueInfoProto { name: o.clone(), ..Default::default() }).collect(),
            initializer: vec![
                scalar,
                TensorProto { name: "w1".into(), dims: vec![3], data_type: 1, raw_data: vec![0; 12], ..Default::default() },
                TensorProto { name: "w4".into(), dims: vec![3, 1, 2, 2], data_type: 1, raw_data: vec![0; 48], ..Default::default() },
                i64s("min", vec![i64::MIN]),
                i64s("neg", vec![-1]),
                i64s("st", vec![0, 0]),
                i64s("en", vec![1]),
                i64s("ax", vec![9]),
            ],
            ..Default::default()
        }),
        ..Default::default()
    };
    let p = dir.path().join("hostile.onnx");
    std::fs::write(&p, m.encode_to_vec()).unwrap();
    let r = cli(&["inspect", p.to_str().unwrap(), "--json"]);
    assert!(!r.stderr.contains("internal error") && !r.stderr.contains("panicked"), "{}", r.stderr);
    assert_eq!(r.code, 0, "{}", r.stderr);
}

/// Calibration folders with a frame no pass should read: a NaN pixel, a constant frame, a
/// file that is not an image. Each is refused naming the file; nothing is written.
#[test]
fn bad_calibration_frames_are_refused_naming_the_file() {
    use pdi_compile::optics::npy::to_bytes;
    let dir = tempfile::tempdir().unwrap();
    let (h, w) = (192, 256);
    let good: Vec<f32> = (0..h * w).map(|i| (i % 97) as f32 / 97.0).collect();
    let mut nan = good.clone();
    nan[1234] = f32::NAN;
    let cases: [(&str, Vec<u8>, &str); 3] = [
        ("nan.npy", to_bytes(&[h, w], &nan), "non-finite"),
        ("flat.npy", to_bytes(&[h, w], &vec![0.5; h * w]), "constant frame"),
        ("broken.png", b"not a png".to_vec(), "broken.png"),
    ];
    for (name, bytes, says) in cases {
        let calib = dir.path().join(format!("calib_{name}"));
        std::fs::create_dir_all(&calib).unwrap();
        std::fs::write(calib.join("a_good.npy"), to_bytes(&[h, w], &good)).unwrap();
        std::fs::write(calib.join(name), bytes).unwrap();
        let out = dir.path().join(format!("out_{name}"));
        let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", "passes/detect-int8.yaml", "--psf", "calib/single_lwir_blur.npy", "--calib", calib.to_str().unwrap(), "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{name}: {}", r.stderr);
        let errors: Vec<&str> = r.stderr.lines().filter(|l| l.starts_with("error:")).collect();
        assert_eq!(errors.len(), 1, "{name}: {}", r.stderr);
        assert!(errors[0].contains(name) && errors[0].contains(says), "{name}: {}", r.stderr);
        assert!(!out.join("model.onnx").exists(), "{name}: wrote a model");
    }
}

/// Frames of another size are area-resized and colour frames converted, each with one
/// warning on stderr that also lands in the report's top-level `warnings`, as does the
/// warning for a folder with fewer frames than the pass asked for.
#[test]
fn odd_calibration_frames_are_converted_with_warnings() {
    let dir = tempfile::tempdir().unwrap();
    let calib = dir.path().join("calib");
    std::fs::create_dir_all(&calib).unwrap();
    for i in 0..3u32 {
        let rgb = image::RgbImage::from_fn(320, 240, |x, y| image::Rgb([((x + i) % 256) as u8, (y % 256) as u8, ((x * y) % 256) as u8]));
        rgb.save(calib.join(format!("{i}.png"))).unwrap();
    }
    let recipe = dir.path().join("int8.yaml");
    std::fs::write(&recipe, recipe_edit("passes/detect-int8.yaml", "calib_frames: 64", "calib_frames: 4, analysis_frames: 2, held_out_frames: 2")).unwrap();
    let out = dir.path().join("out");
    let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "--calib", calib.to_str().unwrap(), "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    let report: serde_json::Value = serde_json::from_str(&r.stdout).unwrap();
    let warnings = report["warnings"].to_string();
    for says in ["area-resized", "converted to luma", "holds 3 frame(s)"] {
        assert!(r.stderr.contains(says), "stderr says '{says}': {}", r.stderr);
        assert!(warnings.contains(says), "report warnings say '{says}': {warnings}");
    }
}

/// A model whose image input takes three channels (thermal frames stored as RGB, averaged in
/// the graph): INT8 calibrates on single-channel frames replicated into the three channels,
/// with a warning, and verify feeds it replicated frames against the single-channel original.
#[test]
fn a_three_channel_input_is_fed_replicated_frames() {
    use pdi_compile::onnx::proto::{AttributeProto, DimensionValue, NodeProto, TypeValue};
    let dir = tempfile::tempdir().unwrap();
    let mut m = load(&repo().join("models/trained/pdinet_v5_tiny_trained.onnx"));
    let g = m.graph.as_mut().unwrap();
    for n in &mut g.node {
        n.input.iter_mut().filter(|i| *i == "image").for_each(|i| *i = "image_gray".into());
    }
    let Some(TypeValue::TensorType(t)) = g.input[0].r#type.as_mut().unwrap().value.as_mut() else { panic!("tensor input") };
    t.shape.as_mut().unwrap().dim[1].value = Some(DimensionValue::DimValue(3));
    let ints = AttributeProto { name: "axes".into(), r#type: 7, ints: vec![1], ..Default::default() };
    let keep = AttributeProto { name: "keepdims".into(), r#type: 2, i: Some(1), ..Default::default() };
    g.node.insert(0, NodeProto { name: "to_gray".into(), op_type: "ReduceMean".into(), input: vec!["image".into()], output: vec!["image_gray".into()], attribute: vec![ints, keep], ..Default::default() });
    let rgb = dir.path().join("rgb.onnx");
    pdi_compile::onnx::save(&m, &rgb).unwrap();

    let recipe = dir.path().join("int8.yaml");
    std::fs::write(&recipe, recipe_edit("passes/detect-int8.yaml", "calib_frames: 64", "calib_frames: 8, analysis_frames: 2, held_out_frames: 2")).unwrap();
    let out = dir.path().join("out");
    // strip-recon recognizes the single-channel reconstruction of a three-channel input.
    let r = cli(&["compile", rgb.to_str().unwrap(), "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stderr.contains("replicated"), "{}", r.stderr);
    // Replication is exact: the lossless compile of the RGB-input model matches the original.
    let f32 = dir.path().join("f32");
    let r = cli(&["compile", rgb.to_str().unwrap(), "--pipeline", "passes/detect-f32.yaml", "--psf", "calib/single_lwir_blur.npy", "-o", f32.to_str().unwrap()]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    // INT8 of a random-weight-like RGB model is loose; its outputs still point where the float
    // model's do (cosine), which outputs of zeros (rel L2 exactly 1) would not.
    for (candidate, max_rel_l2, min_cosine) in [(f32.join("model.onnx"), 1e-5, 0.99999), (out.join("model.onnx"), 1.0, 0.9)] {
        let v = cli(&["verify", "--reference", "models/trained/pdinet_v5_tiny_trained.onnx", "--candidate", candidate.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "--random", "4", "--runs", "0", "--no-tract", "--json"]);
        assert_eq!(v.code, 0, "{}", v.stderr);
        let report: serde_json::Value = serde_json::from_str(&v.stdout).unwrap();
        let e = report["outputs"][0]["ort"]["rel_l2"].as_f64().unwrap();
        let cos = report["outputs"][0]["ort"]["cosine"].as_f64().unwrap();
        assert!(e <= max_rel_l2 && cos >= min_cosine, "{}: rel L2 {e}, cosine {cos}", candidate.display());
    }
}

/// Impossible quantization-aware recovery settings are refused in one line before any
/// calibration or training, and nothing is written.
#[test]
fn bad_qat_settings_are_refused_before_calibration() {
    let dir = tempfile::tempdir().unwrap();
    let qat = std::fs::read_to_string(repo().join("passes/detect-int8-qat.yaml")).unwrap();
    assert!(qat.contains("qat: {steps: 800}"), "the recipe's qat line moved; update this test");
    for (setting, needle) in [("{minutes: 0}", "minutes (a time cap) must be a positive number"), ("{lr: .nan}", "qat: lr must be a positive number"), ("{batch: 0}", "steps and batch must be at least 1"), ("{epochs: 3}", "unknown field `epochs`")] {
        let recipe = dir.path().join("qat.yaml");
        std::fs::write(&recipe, qat.replace("qat: {steps: 800}", &format!("qat: {setting}"))).unwrap();
        let out = dir.path().join("out");
        let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{setting}: {}", r.stderr);
        assert!(r.stderr.contains(needle) && r.stderr.trim().lines().count() == 1, "{setting}: {}", r.stderr);
        assert!(!out.join("model.onnx").exists(), "{setting}: nothing written");
    }
}

/// rknn-qat refuses, in one line and before the toolkit or torch run: bad settings, and a
/// model that is not from rknn-legalize.
#[test]
fn bad_rknn_qat_settings_and_placement_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let qat = std::fs::read_to_string(repo().join("passes/detect-rknn-qat.yaml")).unwrap();
    let misplaced = qat.replace("base: detect-rknn\n", "base: detect-f32\n");
    assert!(qat.contains("rknn-qat: {steps: 800}") && misplaced != qat, "the recipe's lines moved; update this test");
    for (recipe_text, needle) in [
        (qat.replace("rknn-qat: {steps: 800}", "rknn-qat: {steps: 0}"), "steps and batch must be at least 1"),
        (qat.replace("rknn-qat: {steps: 800}", "rknn-qat: {frames: 4}"), "4 frames for batches of 8"),
        (qat.replace("rknn-qat: {steps: 800}", "rknn-qat: {epochs: 3}"), "unknown field `epochs`"),
        (misplaced, "put rknn-legalize before it"),
        (qat.replace("rknn-qat: {steps: 800}", "rknn-hybrid: {fp16: [/no/such/Conv]}"), "'/no/such/Conv', which is not a node"),
    ] {
        let recipe = dir.path().join("qat.yaml");
        std::fs::write(&recipe, &recipe_text).unwrap();
        let out = dir.path().join("out");
        let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{needle}: {}", r.stderr);
        assert!(r.stderr.contains(needle) && r.stderr.trim().lines().count() == 1, "{needle}: {}", r.stderr);
        assert!(!out.join("model.onnx").exists(), "{needle}: nothing written");
    }
}

/// A recipe is checked whole before any pass runs: each mistake exits 2 within 2 s with one
/// line naming the recipe's line, and no output folder appears.
#[test]
fn malformed_recipes_are_refused_before_any_pass_runs() {
    let dir = tempfile::tempdir().unwrap();
    let lossless = "  - promote-constants\n  - strip-recon\n  - bind-psf\n  - fold-constants\n  - fold-psf-gates\n  - fold-bn\n  - dce\n";
    let prune = "  - prune: {ratio: 0.5}\n";
    let cases: Vec<(&str, String, Vec<&str>, &str)> = vec![
        ("recover without prune", format!("{lossless}  - recover: {{steps: 10}}\n"), vec![], "line 10: recover: needs teacher"),
        ("rknn-qat without rknn-legalize", format!("{lossless}  - rknn-qat: {{steps: 10}}\n"), vec![], "needs split-head"),
        ("qat from the original without prune", format!("{lossless}  - quantize: {{qat: {{teacher: original}}}}\n"), vec![], "needs teacher"),
        ("an unknown option in the last pass", format!("{lossless}{prune}  - recover: {{steps: 10}}\n  - cleanup\n  - quantize: {{calib_frame: 8}}\n"), vec![], "line 13: quantize: options of pass quantize: unknown field `calib_frame`"),
        ("a negative step count", format!("{lossless}{prune}  - recover: {{steps: -5}}\n"), vec![], "line 11: recover"),
        ("a missing --calib folder", format!("{lossless}{prune}"), vec!["--calib", "/no/such/frames"], "--calib /no/such/frames: no such folder"),
        ("an unknown pass", format!("{lossless}  - fold-everything\n"), vec![], "unknown pass 'fold-everything'"),
        ("warm-up longer than the steps", format!("{lossless}{prune}  - recover: {{steps: 10, warmup: 10}}\n"), vec![], "warmup (10) must be fewer than steps (10)"),
        ("rknn-hybrid without rknn-legalize", format!("{lossless}  - rknn-hybrid\n"), vec![], "put rknn-legalize before it"),
        ("a time cap of zero minutes", format!("{lossless}{prune}  - recover: {{steps: 10, minutes: 0}}\n"), vec![], "minutes (a time cap) must be a positive number"),
        ("an average that never moves", format!("{lossless}{prune}  - recover: {{steps: 10, ema: 1.0}}\n"), vec![], "ema (the average's decay) must be at least 0 and below 1 (got 1)"),
        ("a qat lr of zero", format!("{lossless}  - quantize: {{qat: {{lr: 0}}}}\n"), vec![], "qat: lr must be a positive number"),
        ("a missing --psf file", lossless.to_string(), vec!["--psf", "/no/such/psf.npy"], "/no/such/psf.npy"),
    ];
    for (what, passes, extra, needle) in cases {
        let recipe = dir.path().join("bad.yaml");
        std::fs::write(&recipe, format!("name: bad\npasses:\n{passes}")).unwrap();
        let out = dir.path().join("out");
        let mut args = vec!["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe.to_str().unwrap(), "-o", out.to_str().unwrap()];
        if !extra.contains(&"--psf") {
            args.extend(["--psf", "calib/single_lwir_blur.npy"]);
        }
        args.extend(extra);
        let t = std::time::Instant::now();
        let r = cli(&args);
        let seconds = t.elapsed().as_secs_f64();
        assert_eq!(r.code, 2, "{what}: {}", r.stderr);
        assert!(r.stderr.contains(needle) && r.stderr.trim().lines().count() == 1, "{what}: {:?} should name {needle:?}", r.stderr);
        assert!(seconds < 2.0, "{what}: refused after {seconds:.2} s");
        assert!(!out.exists(), "{what}: no output folder");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1, "{what}: nothing beside the recipe");
    }
}

/// A compile killed with SIGKILL leaves an existing output folder as it was, and makes no
/// folder at a new path; the next compile removes the temporary sibling it left.
#[test]
fn a_killed_compile_leaves_the_folder_as_it_was() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let args = |out: &Path, recipe: &str| -> Vec<String> {
        ["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", recipe, "--psf", "calib/single_lwir_blur.npy", "-o", out.to_str().unwrap()].iter().map(|s| s.to_string()).collect()
    };
    let r = cli(&args(&out, "passes/detect-f32.yaml").iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(r.code, 0, "{}", r.stderr);
    let listing = |d: &Path| -> Vec<(String, Vec<u8>)> {
        let mut v: Vec<(String, Vec<u8>)> = std::fs::read_dir(d).unwrap().flatten().map(|e| (e.file_name().to_string_lossy().into_owned(), std::fs::read(e.path()).unwrap())).collect();
        v.sort();
        v
    };
    let before = listing(&out);
    let fresh = dir.path().join("fresh");
    for target in [&out, &fresh] {
        // Pruning measures sensitivities for seconds before anything is written.
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_pdi-compile")).args(args(target, "passes/detect-pruned-f32-norecover.yaml")).current_dir(repo()).stderr(std::process::Stdio::null()).spawn().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(1500));
        assert!(child.try_wait().unwrap().is_none(), "the compile ended before it could be killed");
        child.kill().unwrap(); // SIGKILL
        child.wait().unwrap();
    }
    assert!(listing(&out) == before, "the killed compile changed the existing folder");
    assert!(!fresh.exists(), "a folder appeared at the new path");
    // The next compile into the same place replaces the folder whole and leaves no sibling.
    let r = cli(&args(&out, "passes/identity.yaml").iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(r.code, 0, "{}", r.stderr);
    let names: Vec<String> = std::fs::read_dir(dir.path()).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    assert!(names.iter().all(|n| !n.contains("pdi-partial") || n.contains("fresh")), "{names:?}");
    assert!(!out.join("tract.yaml").exists() && out.join("model.onnx").exists());
}

/// A mistyped flag, a missing argument or an unknown command: clap's first line and where the
/// usage is, one line and exit 2, as for every other bad input; `--help` still prints the usage.
#[test]
fn argument_errors_are_one_line() {
    for (args, needle) in [(vec!["compile", "x.onnx", "--pipline", "p.yaml"], "--pipline"), (vec!["compile"], "required"), (vec!["compiel"], "compiel")] {
        let r = cli(&args);
        assert_eq!(r.code, 2, "{args:?}: {}", r.stderr);
        assert!(r.stderr.starts_with("error: ") && r.stderr.contains(needle) && r.stderr.trim_end().lines().count() == 1, "{args:?}:\n{}", r.stderr);
    }
    let r = cli(&["compile", "--help"]);
    assert_eq!(r.code, 0, "{}", r.stderr);
    assert!(r.stdout.contains("Usage:"), "{}", r.stdout);
}
