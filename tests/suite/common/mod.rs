//! Shared test helpers: fixtures, deterministic inputs, running the CLI.
#![allow(dead_code)]

use pdi_compile::onnx::proto::ModelProto;
use pdi_compile::tensor::{DType, Tensor, TensorData};
use std::path::{Path, PathBuf};

pub fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Every committed fixture; fails (never skips) if there are none.
pub fn fixtures() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(repo().join("models/fixtures"))
        .expect("models/fixtures exists")
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "onnx"))
        .collect();
    v.sort();
    assert!(v.len() >= 16, "expected the 16 committed fixtures, found {}", v.len());
    v
}

/// A small deterministic generator (no external crates needed for test data).
pub struct Lcg(pub u64);
impl Lcg {
    pub fn next_f32(&mut self) -> f32 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((self.0 >> 40) as f32) / ((1u64 << 24) as f32)
    }
}

/// Inputs for a model's graph inputs: image-like values in [0, 1); a blur map in [0, 1].
pub fn inputs_for(model: &ModelProto, seed: u64) -> Vec<(String, Tensor)> {
    let g = model.graph.as_ref().unwrap();
    let inits: Vec<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
    let mut rng = Lcg(seed);
    g.input
        .iter()
        .filter(|v| !inits.contains(&v.name.as_str()))
        .map(|v| {
            let t = pdi_compile::ir::shapes::declared(v);
            assert_eq!(t.dtype, Some(DType::F32), "fixture inputs are float");
            let shape = t.static_shape().expect("fixture inputs have static shapes");
            let n = shape.iter().product();
            (v.name.clone(), Tensor::new(shape, TensorData::F32((0..n).map(|_| rng.next_f32()).collect())))
        })
        .collect()
}

pub fn load(path: &Path) -> ModelProto {
    pdi_compile::onnx::load(path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display())).model
}

pub struct CliResult {
    pub code: i32,
    pub stdout: String,
    pub stderr: String,
}

pub fn cli(args: &[&str]) -> CliResult {
    cli_without(args, &[])
}

/// `cli` with the environment variables `unset` removed for the command.
pub fn cli_without(args: &[&str], unset: &[&str]) -> CliResult {
    // On the CPU: the claims about training (the same bytes, one process against ranks) are
    // the CPU's; a GPU's kernels are not deterministic.
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_pdi-compile"));
    for k in unset {
        command.env_remove(k);
    }
    let out = command.args(args).current_dir(repo()).env("CUDA_VISIBLE_DEVICES", "").output().unwrap();
    CliResult {
        code: out.status.code().unwrap_or(-1),
        stdout: String::from_utf8_lossy(&out.stdout).into_owned(),
        stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
    }
}

/// Relative L2 error of `b` against `a`.
pub fn rel_l2(a: &Tensor, b: &Tensor) -> f64 {
    let (a, b) = (a.data.to_f64(), b.data.to_f64());
    let num: f64 = a.iter().zip(&b).map(|(x, y)| (x - y).powi(2)).sum();
    let den: f64 = a.iter().map(|x| x * x).sum();
    (num / den.max(1e-30)).sqrt()
}

/// The held-out evaluation set of the trained models (models/trained/MODEL_CARD.md), made in
/// `dir` by the Rust physics pipeline: 200 labelled 256x192 frames (seed 2, q 90); returns
/// the frames' folder.
pub fn eval_set(dir: &Path) -> PathBuf {
    eval_frames(dir, 200)
}

/// The first `n` frames of the held-out set's recipe (for tests that need a few frames).
/// Generated once per test process and shared: the tests only read it (`_dir` is where each
/// test writes its own files).
pub fn eval_frames(_dir: &Path, n: usize) -> PathBuf {
    eval_frames_at(n, "256x192")
}

/// The held-out scenes' first `n` frames at `size` (`256x192`, or the sensor's `640x480`).
pub fn eval_frames_at(n: usize, size: &str) -> PathBuf {
    static ROOT: std::sync::OnceLock<tempfile::TempDir> = std::sync::OnceLock::new();
    static MADE: std::sync::Mutex<Vec<String>> = std::sync::Mutex::new(Vec::new());
    // Under target/tmp: a static is never dropped, so this folder outlives the process there.
    let key = if size == "256x192" { n.to_string() } else { format!("{n}-{size}") };
    let root = ROOT.get_or_init(|| tempfile::tempdir_in(env!("CARGO_TARGET_TMPDIR")).unwrap()).path().join(&key);
    // Held while generating: a second test wanting the same set waits instead of racing.
    let mut made = MADE.lock().unwrap_or_else(|e| e.into_inner());
    if !made.contains(&key) {
        let psf = root.join("psf");
        let r = cli(&["psf", "simulate", "--lens", "calib/lens_single_lwir.yaml", "-o", psf.to_str().unwrap()]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let set = root.join("eval");
        let r = cli(&["dataset", set.to_str().unwrap(), "--psf", psf.to_str().unwrap(), "--n", &n.to_string(), "--q", "90", "--seed", "2", "--min-box", "16", "--out-size", size]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        made.push(key);
    }
    root.join("eval").join("degraded")
}

/// The line of the INT8 recipes that runs `space-to-depth`: the tests of what torch trains
/// take it out, since the pipeline lowers its blocks before any torch training.
pub const SPACE_TO_DEPTH: &str = "  - space-to-depth\n";

/// The text of the shipped recipe `recipe` (repo-relative) with `from` replaced by `to`;
/// fails if the recipe no longer has `from` (an edit that replaces nothing tests nothing).
pub fn recipe_edit(recipe: &str, from: &str, to: &str) -> String {
    let text = std::fs::read_to_string(repo().join(recipe)).unwrap_or_else(|e| panic!("{recipe}: {e}"));
    assert!(text.contains(from), "{recipe} has no '{from}' to replace");
    text.replace(from, to)
}

/// detect-int8 with every convolution a candidate for INT8, the stem and the detector's last
/// convolutions' inputs included (`narrow_float: 0`, no `float_head_inputs`, and no 3-D
/// rewrite after it), without `measured_bias` (its own test turns it on): for tests of the
/// quantizer on every layer, since the recipe keeps layers narrower than 16 channels float
/// and most of the fixtures' and the tiny model's layers are that narrow.
pub fn every_layer_int8() -> String {
    recipe_edit("passes/detect-int8.yaml", "measured_bias: true, float_head_inputs: true, narrow_float: 16}\n  - narrow-convs-nchw\n", "narrow_float: 0}\n")
}
