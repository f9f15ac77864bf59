//! `pdi-compile run` and the `deploy::Detector` behind it: the detections `verify` decodes, on
//! every head the toolchain emits, in the camera frame's coordinates, drawn where they are.

use crate::common::*;
use serde_json::Value;
use std::path::Path;

const V5: &str = "models/trained/pdinet_v5_w0.25_trained.onnx";
const PSF: &str = "calib/single_lwir_blur.npy";

fn json(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))).unwrap()
}

fn run(args: &[&str]) -> Value {
    let r = cli(&[&["run"], args].concat());
    assert_eq!(r.code, 0, "{}", r.stderr);
    serde_json::from_str(&r.stdout).unwrap()
}

fn compile(recipe: &str, out: &Path, extra: &[&str]) {
    let r = cli(&[&["compile", V5, "--pipeline", recipe, "--psf", PSF, "-o", out.to_str().unwrap()], extra].concat());
    assert_eq!(r.code, 0, "{}", r.stderr);
}

fn map50_95(v: &Value) -> f64 {
    v["map50_95"].as_f64().unwrap_or_else(|| panic!("no map50_95 in {v}"))
}

/// Boxes (xyxy) and scores per frame from run's detections.json (COCO xywh).
fn boxes(path: &Path, frames: usize) -> Vec<Vec<([f32; 4], f32, usize)>> {
    let mut per = vec![Vec::new(); frames];
    for d in coco_results(path) {
        per[d.image_id - 1].push((d.bbox, d.score, d.class));
    }
    per
}

struct Found {
    image_id: usize,
    file: String,
    class: usize,
    score: f32,
    /// xyxy
    bbox: [f32; 4],
}

/// A COCO results list (bbox xywh) as written by `run` and `run_rknn.py`.
fn coco_results(path: &Path) -> Vec<Found> {
    json(path)
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            let b: Vec<f32> = d["bbox"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap() as f32).collect();
            Found {
                image_id: d["image_id"].as_u64().unwrap() as usize,
                file: d["file_name"].as_str().unwrap().to_string(),
                class: d["category_id"].as_u64().unwrap() as usize,
                score: d["score"].as_f64().unwrap() as f32,
                bbox: [b[0], b[1], b[0] + b[2], b[1] + b[3]],
            }
        })
        .collect()
}

#[test]
fn run_detects_what_an_independent_decoder_finds_and_scores_the_same_map() {
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    let out = dir.path().join("run");
    let r = run(&[V5, "--frames", data.to_str().unwrap(), "--psf", PSF, "--conf", "0.001", "--engine", "ort", "-o", out.to_str().unwrap(), "--json"]);
    assert_eq!(r["frames"], 200);
    assert_eq!(r["labelled_frames"], 200);

    // An independent decoder: models/pdinet/evaluate.py (numpy decode and NMS, Python's ONNX
    // Runtime, PIL's PNG reader) on the same frames, at conf 0.001 and the head's IoU.
    let python = std::env::var("PDI_PYTHON").expect("PDI_PYTHON is not set: run the suite with scripts/test, which installs onnxruntime and pycocotools");
    let theirs = dir.path().join("evaluate.json");
    let e = std::process::Command::new(python)
        .current_dir(repo())
        .args(["models/pdinet/evaluate.py", "--model", V5, "--data", data.to_str().unwrap(), "--psf", PSF, "--detections", theirs.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(e.status.success(), "evaluate.py: {}", String::from_utf8_lossy(&e.stderr));
    let summary: Value = serde_json::from_slice(&e.stdout).unwrap();
    let (got, expected) = (boxes(&out.join("detections.json"), 200), boxes(&theirs, 200));
    let mut compared = 0;
    for (i, (got, expected)) in got.iter().zip(&expected).enumerate() {
        assert_eq!(got.len(), expected.len(), "frame {i}: detection count");
        for ((b, s, c), (eb, es, ec)) in got.iter().zip(expected) {
            assert_eq!(c + 1, *ec, "frame {i}: class (evaluate.py numbers COCO categories from 1)");
            assert!((s - es).abs() <= 1e-5, "frame {i}: score {s} against {es}");
            assert!(b.iter().zip(eb).all(|(x, y)| (x - y).abs() <= 1e-4 * y.abs().max(1.0)), "frame {i}: box {b:?} against {eb:?}");
            compared += 1;
        }
    }
    assert!(compared > 1000, "only {compared} detections compared");

    let v = cli(&["verify", "--reference", V5, "--candidate", V5, "--data", data.to_str().unwrap(), "--psf", PSF, "--runs", "0", "--no-tract", "--json"]);
    assert_eq!(v.code, 0, "{}", v.stderr);
    let v: Value = serde_json::from_str(&v.stdout).unwrap();
    let (ours, theirs) = (map50_95(&r["map_labels"]), map50_95(&v["detection"]["candidate_vs_labels"]));
    assert!((ours - theirs).abs() < 1e-12, "run's mAP {ours} against verify's {theirs}");
    let python_map = summary["map50_95"].as_f64().unwrap();
    assert!((ours - python_map).abs() <= 5e-5, "run's mAP {ours} against evaluate.py's (pycocotools) {python_map}");
    assert!(ours > 0.5, "the trained model detects: mAP {ours}");
    // The stages are measured and add up to the frame rate.
    let l = &r["latency"];
    let total: f64 = ["preprocess", "inference", "decode_nms"].iter().map(|s| l[s]["share"].as_f64().unwrap()).sum();
    assert!((total - 1.0).abs() < 1e-9 && l["frames_per_second"].as_f64().unwrap() > 0.0, "{l}");
    for f in ["run.json", "contact_sheet.png", "labels/000199.txt", "images/000199.png"] {
        assert!(out.join(f).is_file(), "{f} written");
    }
}

#[test]
fn run_on_the_rknn_onnx_matches_the_unlegalized_model() {
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    let rknn = dir.path().join("rknn");
    compile("passes/detect-rknn.yaml", &rknn, &["--target", "rknn"]);
    let r = run(&[rknn.to_str().unwrap(), "--frames", data.to_str().unwrap(), "--compare", V5, "--psf", PSF, "-o", dir.path().join("run").to_str().unwrap(), "--json"]);
    let c = &r["compare"];
    // rknn-legalize is lossless in float: the split head decoded in Rust finds the same boxes.
    assert_eq!((c["only_this"].as_u64(), c["only_other"].as_u64()), (Some(0), Some(0)), "{c}");
    assert!(map50_95(&c["agreement"]) > 0.999, "{c}");
    assert!(r["detections"].as_u64().unwrap() > 100, "{r}");
}

#[test]
fn a_roi_artifact_reports_boxes_in_the_full_frame_and_verifys_agreement() {
    let dir = tempfile::tempdir().unwrap();
    let data = eval_set(dir.path());
    let scene = dir.path().join("roi.yaml");
    std::fs::write(&scene, "roi: {x: 0, y: 64, w: 256, h: 128}\n").unwrap();
    let roi = dir.path().join("roi");
    compile("passes/detect-f32.yaml", &roi, &["--scene", scene.to_str().unwrap()]);
    let out = dir.path().join("run");
    let r = run(&[roi.to_str().unwrap(), "--frames", data.to_str().unwrap(), "--compare", V5, "--psf", PSF, "-o", out.to_str().unwrap(), "--json"]);
    // In the ROI's own coordinates every centre would lie above y = 128; in the frame's, below 64 none.
    let centres: Vec<f32> = boxes(&out.join("detections.json"), 200).iter().flatten().map(|(b, _, _)| (b[1] + b[3]) / 2.0).collect();
    assert!(centres.len() > 100, "{} detections", centres.len());
    assert!(centres.iter().all(|&y| y >= 60.0), "a box centre above the ROI: {:?}", centres.iter().copied().fold(f32::MAX, f32::min));
    assert!(centres.iter().any(|&y| y > 140.0), "no box in the ROI's lower half: coordinates are the crop's");
    let v = cli(&["verify", "--reference", V5, "--candidate", roi.join("model.onnx").to_str().unwrap(), "--data", data.to_str().unwrap(), "--psf", PSF, "--runs", "0", "--no-tract", "--json"]);
    assert_eq!(v.code, 0, "{}", v.stderr);
    let v: Value = serde_json::from_str(&v.stdout).unwrap();
    let (ours, theirs) = (map50_95(&r["compare"]["agreement"]), map50_95(&v["detection"]["agreement"]));
    assert!((ours - theirs).abs() < 1e-12, "run's agreement {ours} against verify's {theirs}");
}

/// The 1st and 99th percentiles of a 16-bit frame's values, as fractions of full scale.
fn stretch(values: &[u16]) -> (f32, f32) {
    let mut s: Vec<f32> = values.iter().map(|&v| v as f32 / 65535.0).collect();
    s.sort_by(f32::total_cmp);
    let at = |q: f64| s[((s.len() - 1) as f64 * q).round() as usize];
    (at(0.01), at(0.99))
}

#[test]
fn pictures_show_each_box_in_its_class_colour_over_the_stretched_frame() {
    let dir = tempfile::tempdir().unwrap();
    let data = eval_frames(dir.path(), 8);
    let frame = data.join("000003.png");
    let out = dir.path().join("run");
    run(&[V5, "--frames", frame.to_str().unwrap(), "--psf", PSF, "-o", out.to_str().unwrap(), "--json"]);
    let dets = &boxes(&out.join("detections.json"), 1)[0];
    assert!(!dets.is_empty(), "nothing detected on the test frame");
    let pic = image::open(out.join("images/000003.png")).unwrap().to_rgb8();
    let raw = image::open(&frame).unwrap().to_luma16();
    assert_eq!(pic.dimensions(), raw.dimensions());
    // The best box's left edge, halfway down, is its class's colour (drawn last, on top).
    let (b, _, class) = dets[0];
    let (x, y) = (b[0].round().max(0.0) as u32, ((b[1] + b[3]) / 2.0).round() as u32);
    assert_eq!(pic.get_pixel(x, y).0, pdi_compile::deploy::draw::class_colour(class), "left edge of {b:?}");
    // Far from every box and its tag, the frame itself, stretched: gray, of the frame's value.
    let (lo, hi) = stretch(raw.as_raw());
    let near = |x: f32, y: f32| dets.iter().any(|(b, _, _)| x > b[0] - 130.0 && x < b[2].max(b[0] + 130.0) + 4.0 && y > b[1] - 16.0 && y < b[3] + 4.0);
    let mut checked = 0;
    for (x, y, p) in pic.enumerate_pixels().filter(|(x, y, _)| !near(*x as f32, *y as f32)) {
        let v = raw.get_pixel(x, y).0[0] as f32 / 65535.0;
        let expected = ((v - lo) * 255.0 / (hi - lo)).round().clamp(0.0, 255.0) as u8;
        assert_eq!(p.0, [expected; 3], "pixel ({x}, {y})");
        checked += 1;
    }
    assert!(checked > 10_000, "only {checked} frame pixels checked");
    let sheet = image::open(out.join("contact_sheet.png")).unwrap();
    assert!(sheet.width() >= pic.width() && sheet.height() > pic.height(), "contact sheet {}x{}", sheet.width(), sheet.height());
}

#[test]
fn the_example_prints_detections_of_a_compiled_artifact() {
    let dir = tempfile::tempdir().unwrap();
    let frames = eval_frames(dir.path(), 3);
    let art = dir.path().join("f32");
    compile("passes/detect-f32.yaml", &art, &[]);
    // cargo test builds the examples beside the test binary's folder.
    let exe = std::env::current_exe().unwrap();
    let example = exe.parent().unwrap().parent().unwrap().join("examples/detect");
    assert!(example.is_file(), "{} not built", example.display());
    let out = std::process::Command::new(&example).args([art.to_str().unwrap(), frames.to_str().unwrap()]).output().unwrap();
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let lines: Vec<&str> = stdout.lines().skip(1).collect();
    assert!(lines.len() >= 3 && lines.iter().all(|l| l.split(' ').count() == 7), "{stdout}");
    // The same detections as `run` with the artifact's defaults.
    let r = run(&[art.to_str().unwrap(), "--frames", frames.to_str().unwrap(), "-o", dir.path().join("run").to_str().unwrap(), "--json"]);
    assert_eq!(r["detections"].as_u64(), Some(lines.len() as u64), "{stdout}");
}

#[test]
fn bad_frames_exit_2_naming_the_file_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let data = eval_frames(dir.path(), 8);
    let good = std::fs::read(data.join("000000.png")).unwrap();
    let float_tiff = {
        let img = image::Rgb32FImage::from_pixel(8, 8, image::Rgb([0.5, 0.5, 0.5]));
        let mut c = std::io::Cursor::new(Vec::new());
        image::DynamicImage::ImageRgb32F(img).write_to(&mut c, image::ImageFormat::Tiff).unwrap();
        c.into_inner()
    };
    let mut nan_npy = b"\x93NUMPY\x01\x00".to_vec();
    let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 2), }";
    let pad = 64 - (10 + header.len() + 1) % 64;
    let header = format!("{header}{}\n", " ".repeat(pad));
    nan_npy.extend((header.len() as u16).to_le_bytes());
    nan_npy.extend(header.as_bytes());
    for v in [0.5f32, f32::NAN, 0.1, 0.2] {
        nan_npy.extend(v.to_le_bytes());
    }
    let cases: Vec<(&str, Vec<u8>)> = vec![
        ("text.png", b"not an image".to_vec()),
        ("empty.png", Vec::new()),
        ("truncated.png", good[..good.len() / 2].to_vec()),
        ("float.tif", float_tiff),
        ("nan.npy", nan_npy),
    ];
    for (name, bytes) in cases {
        let frames = dir.path().join(format!("frames-{name}"));
        std::fs::create_dir(&frames).unwrap();
        std::fs::write(frames.join("000000.png"), &good).unwrap();
        std::fs::write(frames.join(name), bytes).unwrap();
        let out = dir.path().join(format!("out-{name}"));
        let r = cli(&["run", V5, "--frames", frames.to_str().unwrap(), "--psf", PSF, "-o", out.to_str().unwrap()]);
        assert_eq!(r.code, 2, "{name}: {}", r.stderr);
        assert!(r.stderr.lines().count() == 1 && r.stderr.contains(name), "{name}: {}", r.stderr);
        assert!(!out.exists(), "{name}: an output folder was left");
    }
    let r = cli(&["run", V5, "--frames", dir.path().join("missing.png").to_str().unwrap(), "--psf", PSF, "-o", dir.path().join("o").to_str().unwrap()]);
    assert_eq!(r.code, 2);
    assert!(r.stderr.lines().count() == 1 && r.stderr.contains("missing.png"), "{}", r.stderr);
}

/// Detections (class, score, xyxy) per file name from a COCO results list.
fn by_file(path: &Path) -> std::collections::BTreeMap<String, Vec<(usize, f32, [f32; 4])>> {
    let mut m = std::collections::BTreeMap::<String, Vec<_>>::new();
    for d in coco_results(path) {
        m.entry(d.file).or_default().push((d.class, d.score, d.bbox));
    }
    m
}

#[test]
fn run_rknn_py_on_the_simulator_finds_what_run_finds() {
    let dir = tempfile::tempdir().unwrap();
    let frames = eval_frames(dir.path(), 6);
    let rknn = dir.path().join("rknn");
    compile("passes/detect-rknn.yaml", &rknn, &["--target", "rknn"]);
    assert!(rknn.join("run_rknn.py").is_file(), "the RKNN folder carries its runner");
    run(&[rknn.to_str().unwrap(), "--frames", frames.to_str().unwrap(), "-o", dir.path().join("run").to_str().unwrap(), "--json"]);
    let python = pdi_compile::pyenv::toolkit_python().unwrap();
    let sim = dir.path().join("sim.json");
    // The toolkit's simulator of the float model: what differs from `run` on ONNX Runtime is
    // the 8-bit input the NPU is fed and the simulator's FP16 arithmetic.
    let out = std::process::Command::new(python).arg(rknn.join("run_rknn.py")).arg(&frames).args(["--simulate", "--float", "--out"]).arg(&sim).current_dir(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let (ours, theirs) = (by_file(&dir.path().join("run/detections.json")), by_file(&sim));
    let (mut confident, mut matched) = (0, 0);
    for (file, dets) in &ours {
        for (c, s, b) in dets.iter().filter(|d| d.1 >= 0.4) {
            confident += 1;
            let found = theirs.get(file).into_iter().flatten().any(|(c2, s2, b2)| c2 == c && (s - s2).abs() < 0.05 && pdi_compile::detect::iou(b, b2) > 0.9);
            matched += usize::from(found);
        }
    }
    assert!(confident >= 10, "only {confident} confident detections to compare");
    assert!(matched as f64 >= 0.95 * confident as f64, "run_rknn.py matched {matched} of run's {confident} confident detections");
}
