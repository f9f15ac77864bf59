//! `pdi-compile rknn-convert DIR`: build DIR/model.rknn with RKNN-Toolkit2 and prove it.
//!
//! Runs the toolkit (2.5.0, in its own venv under the cache folder, installed on first use)
//! on DIR/rknn.yaml, then its simulator on validation frames the calibration never saw, and
//! compares every output, and every channel group of the score outputs on its own, with ONNX
//! Runtime running DIR/model.onnx in float on the same frames. Scores get their own check
//! because they are what INT8 loses first: a score tensor sharing a range with pixel
//! coordinates quantizes to all zeros while the boxes still look fine. Also reported: the
//! layers the toolkit placed on the CPU (none is the only acceptable answer for a model
//! made of NPU ops), and how many detections the two agree on after post-processing.

use super::rknn::RknnConfig;
use super::rknn_toolkit::{self, npu_input, pixels};
use crate::analysis::head::HeadKind;
use crate::calib_frames::calibration_frames;
use crate::detect::split_head::{detect, HeadLayout};
use crate::detect::{iou, Detection};
use crate::fsutil::write_atomic;
use crate::metrics::tensor_error::{ErrorSums, TensorError};
use crate::runtime::{ort_runtime::OrtRuntime, Runtime};
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Context, Result};
use serde::Serialize;
use std::collections::HashMap;
use std::path::PathBuf;
use std::time::Instant;

/// Seed of the validation frames; the calibration set uses seed 0.
const VALIDATION_SEED: u64 = 1_000_003;
/// One step of an 8-bit output over [0, 1] (the NPU writes its sigmoid scores as int8): an
/// output whose simulation never differs from ORT by this much agrees to the NPU's output
/// resolution, whatever its cosine. That is the case of a level with no object in the
/// validation frames: ORT's scores there are ~1e-5 everywhere, the NPU's exactly 0, and
/// their cosine (0) measures nothing.
pub(crate) const OUTPUT_STEP: f64 = 1.0 / 255.0;

pub struct ConvertRequest {
    pub dir: PathBuf,
    /// Validation frames (PNG/TIFF/.npy); simulated when absent.
    pub data: Option<PathBuf>,
    pub frames: usize,
    /// Lowest acceptable cosine for every output and channel group.
    pub min_cosine: f64,
    /// Float model to compare with instead of DIR/model.onnx.
    pub reference: Option<PathBuf>,
}

#[derive(Serialize)]
pub struct Agreement {
    pub name: String,
    #[serde(flatten)]
    pub error: TensorError,
}

#[derive(Serialize)]
pub struct ConvertReport {
    pub rknn: String,
    pub toolkit: String,
    pub seconds: f64,
    pub validation: String,
    /// What set the activation ranges: the toolkit's calibration, or rknn-qat's trained points.
    pub quantization: String,
    /// The float model compared with.
    pub reference: String,
    pub outputs: Vec<Agreement>,
    /// Channel groups: objectness and class channels of the score outputs, all levels.
    pub groups: Vec<Agreement>,
    /// With trained points: the simulator against the trained QDQ model (DIR/model.onnx
    /// quantized at those points) on ONNX Runtime's reference kernels, i.e. whether the NPU
    /// runs what was trained.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub trained_qdq: Vec<Agreement>,
    pub npu_layers: usize,
    pub cpu_layers: Vec<String>,
    /// Layers rknn.yaml asks to build in FP16 (its fp16_layers, by node name).
    pub fp16_layers: Vec<String>,
    /// How many of them the toolkit's quantization config holds: it skips, with a warning in
    /// the build log, a span whose tensors its own fusions renamed.
    pub fp16_layers_built: usize,
    /// Detections after post-processing (conf 0.25, NMS 0.45): ORT's, the simulator's, and
    /// how many of ORT's the simulator found (same class, IoU ≥ 0.5).
    pub detections_ort: usize,
    pub detections_rknn: usize,
    pub detections_matched: usize,
    /// The score threshold detections were matched at (rknn.yaml's post-processing).
    pub score_threshold: f32,
    pub min_cosine: f64,
    pub failures: Vec<String>,
    pub passed: bool,
}

pub fn convert(req: &ConvertRequest) -> Result<ConvertReport> {
    let t = Instant::now();
    let dir = &req.dir;
    let text = std::fs::read_to_string(dir.join("rknn.yaml")).with_context(|| format!("{} has no rknn.yaml: compile into it with --target rknn first", dir.display()))?;
    let config: RknnConfig = yaml_serde::from_str(&text).map_err(|e| anyhow!("{}: {e}", dir.join("rknn.yaml").display()))?;
    let model = crate::onnx::load(&dir.join(&config.model))?.model;
    let reference_path = req.reference.clone().unwrap_or_else(|| dir.join(&config.model));
    let reference_model = crate::onnx::load(&reference_path)?.model;
    let reference_outputs: Vec<&str> = reference_model.graph.iter().flat_map(|g| &g.output).map(|o| o.name.as_str()).collect();
    if let Some(missing) = config.outputs.iter().find(|o| !reference_outputs.contains(&o.as_str())) {
        bail!("{} has no output '{missing}': the reference must be the same rknn-legalize model (e.g. from passes/detect-rknn.yaml)", reference_path.display());
    }
    if req.frames == 0 {
        bail!("--frames must be at least 1");
    }

    let [_, _, h, w] = config.input.shape;
    let set = calibration_frames(req.data.as_deref(), req.frames, h, w, VALIDATION_SEED)?;
    let work = tempfile::tempdir()?;
    let mut frame_paths = Vec::new();
    for (i, f) in set.frames.iter().enumerate() {
        let p = work.path().join(format!("frame_{i:04}.npy"));
        std::fs::write(&p, crate::optics::npy::to_bytes(&f.image.shape, &pixels(f.image.as_f32().unwrap_or(&[]))))?;
        frame_paths.push(p);
    }
    let rknn_tmp = dir.join("model.rknn.tmp");
    let job = serde_json::json!({
        "config": config,
        "dir": std::path::absolute(dir)?,
        "frames": frame_paths,
        "out_dir": work.path(),
        "rknn": std::path::absolute(&rknn_tmp)?,
    });
    eprintln!("rknn-convert: building {} with rknn-toolkit2 and simulating {} frames", dir.join("model.rknn").display(), set.frames.len());
    let log_path = dir.join("rknn_build.log");
    let result = rknn_toolkit::run(work.path(), &job, Some(&log_path)).map_err(|e| {
        let _ = std::fs::remove_file(&rknn_tmp);
        anyhow!("rknn-toolkit2 failed: {e:#} (full log: {})", log_path.display())
    })?;
    std::fs::rename(&rknn_tmp, dir.join("model.rknn"))?;
    let log = String::from_utf8_lossy(&std::fs::read(&log_path)?).into_owned();

    let placement = placement(&log);
    if placement.is_empty() {
        bail!("no layer placement table in {}: this toolkit version logs differently", log_path.display());
    }
    let cpu_layers: Vec<String> = placement.iter().filter(|l| l.target == "CPU" && l.op != "InputOperator" && l.op != "OutputOperator").map(|l| format!("{} {}", l.op, l.name)).collect();
    let npu_layers = placement.iter().filter(|l| l.target == "NPU").count();

    let mut ort = OrtRuntime::new(&reference_model)?;
    let trained = &config.quantization.trained_points;
    let mut trained_qdq = match trained.is_empty() {
        true => None,
        false => {
            // Points on the toolkit's own tensors (not graph values) cannot be emulated; points
            // its fused activations never round are not its arithmetic.
            let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
            let mut points = super::rknn_points::by_value(trained);
            let splits = crate::quant::at_points::splits(g, |v| points.contains_key(v));
            let values: std::collections::HashSet<&str> = g.node.iter().flat_map(|n| &n.output).chain(g.input.iter().map(|i| &i.name)).chain(&splits.sums).map(String::as_str).collect();
            let fused: Vec<String> = points.keys().filter(|v| super::rknn_points::fused_away(g, v, &splits.outputs).is_some()).cloned().collect();
            points.retain(|v, _| values.contains(v.as_str()) && !fused.contains(v));
            let (qdq, _) = crate::quant::at_points::emit(&model, &points)?;
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
            let rt = OrtRuntime::with_options(&qdq, ort::session::builder::GraphOptimizationLevel::Disable, threads)?;
            Some((rt, config.outputs.iter().map(|n| (n.clone(), ErrorSums::default())).collect::<Vec<_>>()))
        }
    };
    let layout = &config.head_layout;
    let mut per_output: Vec<(String, ErrorSums)> = config.outputs.iter().map(|n| (n.clone(), ErrorSums::default())).collect();
    let mut per_group: Vec<(&'static str, ErrorSums)> = Vec::new();
    let (mut n_ort, mut n_rknn, mut matched) = (0, 0, 0);
    for (i, f) in set.frames.iter().enumerate() {
        let x = npu_input(f.image.as_f32().unwrap_or(&[]));
        let feed = [(config.input.name.clone(), Tensor::f32(f.image.shape.clone(), x))];
        let reference: HashMap<String, Tensor> = ort.run(&feed)?.into_iter().collect();
        if let Some((rt, sums)) = trained_qdq.as_mut() {
            let q: HashMap<String, Tensor> = rt.run(&feed)?.into_iter().collect();
            for (name, s) in sums.iter_mut() {
                let (a, b) = (q.get(name).ok_or_else(|| anyhow!("the trained QDQ model gave no output '{name}'"))?, crate::optics::npy::read(&work.path().join(format!("{i:04}_{name}.npy")))?);
                s.add(a.data.to_f64().into_iter(), b.data.iter().map(|&v| v as f64));
            }
        }
        let mut simulated = HashMap::new();
        for (name, sums) in per_output.iter_mut() {
            let a = crate::optics::npy::read(&work.path().join(format!("{i:04}_{name}.npy")))?;
            let r = reference.get(name).ok_or_else(|| anyhow!("ONNX Runtime gave no output '{name}'"))?;
            if a.data.len() != r.len() {
                bail!("the simulator's '{name}' has shape {:?}, ONNX Runtime's {:?}", a.shape, r.shape);
            }
            let rv = r.data.to_f64();
            sums.add(rv.iter().copied(), a.data.iter().map(|&v| v as f64));
            for (group, channels) in score_groups(layout, name, &r.shape) {
                let idx = group_index(&mut per_group, group);
                let plane = r.shape[2] * r.shape[3];
                per_group[idx].1.add(channels.iter().flat_map(|&c| rv[c * plane..(c + 1) * plane].iter().copied()), channels.iter().flat_map(|&c| a.data[c * plane..(c + 1) * plane].iter().map(|&v| v as f64)));
            }
            simulated.insert(name.clone(), Tensor::f32(r.shape.clone(), a.data));
        }
        let pp = &config.post_processing;
        let (d_ort, _) = detect(layout, &reference, pp.score_threshold, pp.nms_iou, pp.max_detections)?;
        let (d_rknn, _) = detect(layout, &simulated, pp.score_threshold, pp.nms_iou, pp.max_detections)?;
        n_ort += d_ort.len();
        n_rknn += d_rknn.len();
        matched += count_matched(&d_ort, &d_rknn);
    }
    let outputs: Vec<Agreement> = per_output.into_iter().map(|(name, s)| Agreement { name, error: s.finish() }).collect();
    let groups: Vec<Agreement> = per_group.into_iter().map(|(name, s)| Agreement { name: name.into(), error: s.finish() }).collect();
    let mut failures: Vec<String> = outputs
        .iter()
        .chain(&groups)
        .filter(|a| !(a.error.cosine >= req.min_cosine) && !(a.error.max_abs < OUTPUT_STEP))
        .map(|a| format!("{}: cosine {:.5} < {}", a.name, a.error.cosine, req.min_cosine))
        .collect();
    failures.extend(cpu_layers.iter().map(|l| format!("placed on the CPU: {l}")));
    let fp16_built = result["fp16_built"].as_u64().unwrap_or(0) as usize;
    if fp16_built < config.quantization.fp16_layers.len() {
        crate::warn::warn(format!(
            "rknn-convert: the toolkit built {fp16_built} of the {} FP16 spans rknn.yaml asks for; it skips a span whose tensors its fusions renamed (\"Cannot find the quantization layer\" in {}), and those layers run in INT8; name the layer's fused neighbour instead",
            config.quantization.fp16_layers.len(),
            dir.join("rknn_build.log").display()
        ));
    }
    let report = ConvertReport {
        rknn: dir.join("model.rknn").display().to_string(),
        toolkit: result["toolkit"].as_str().unwrap_or("?").to_string(),
        seconds: t.elapsed().as_secs_f64(),
        validation: set.source,
        quantization: {
            let absent = result["ranges_absent"].as_array().map_or(0, Vec::len);
            let input = match config.input.range {
                Some([lo, hi]) => format!("; the input over [{lo}, {hi}]"),
                None => String::new(),
            };
            match trained.is_empty() {
                true => format!("the toolkit's own calibration ({} frames){input}", config.quantization.dataset_frames),
                false => format!("rknn-qat's trained points ({}){input}: {} ranges written into the toolkit's quantization config, {absent} absent from it", trained.len(), result["ranges_set"]),
            }
        },
        reference: reference_path.display().to_string(),
        outputs,
        trained_qdq: trained_qdq.map(|(_, sums)| sums.into_iter().map(|(name, s)| Agreement { name, error: s.finish() }).collect()).unwrap_or_default(),
        groups,
        npu_layers,
        cpu_layers,
        fp16_layers: config.quantization.fp16_layers.iter().map(|l| l.node.clone()).collect(),
        fp16_layers_built: fp16_built,
        detections_ort: n_ort,
        detections_rknn: n_rknn,
        detections_matched: matched,
        score_threshold: config.post_processing.score_threshold,
        min_cosine: req.min_cosine,
        passed: failures.is_empty(),
        failures,
    };
    write_atomic(&dir.join("rknn_report.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    Ok(report)
}

/// One row of the toolkit's placement table.
struct Placed {
    op: String,
    target: String,
    name: String,
}

/// The verbose build log's table: "D RKNN: [time] ID OpType DataType Target … FullName".
fn placement(log: &str) -> Vec<Placed> {
    let mut rows = std::collections::BTreeMap::new();
    for line in log.lines() {
        let Some(rest) = line.split_once("RKNN: [").and_then(|(_, r)| r.split_once(']')).map(|(_, r)| r) else { continue };
        let t: Vec<&str> = rest.split_whitespace().collect();
        if let (Some(Ok(id)), Some(target)) = (t.first().map(|s| s.parse::<usize>()), t.get(3).filter(|s| matches!(**s, "CPU" | "NPU" | "GPU"))) {
            rows.insert(id, Placed { op: t[1].to_string(), target: target.to_string(), name: t.last().unwrap_or(&"?").to_string() });
        }
    }
    rows.into_values().collect()
}

fn group_index(groups: &mut Vec<(&'static str, ErrorSums)>, name: &'static str) -> usize {
    if let Some(i) = groups.iter().position(|g| g.0 == name) {
        return i;
    }
    groups.push((name, ErrorSums::default()));
    groups.len() - 1
}

/// Channel groups of a score output: YOLOv5 scores hold objectness then classes per anchor.
fn score_groups(layout: &HeadLayout, output: &str, shape: &[usize]) -> Vec<(&'static str, Vec<usize>)> {
    let Some(level) = layout.levels.iter().find(|l| l.scores == output) else { return vec![] };
    let nc = layout.classes;
    match layout.kind {
        HeadKind::Yolov5Anchor => {
            let anchors = level.anchors.len();
            vec![("objectness", (0..anchors).map(|a| a * (1 + nc)).collect()), ("classes", (0..anchors).flat_map(|a| (1..=nc).map(move |k| a * (1 + nc) + k)).collect())]
        }
        _ => vec![("classes", (0..shape.get(1).copied().unwrap_or(0)).collect())],
    }
}

/// Reference detections found by the candidate: same class, IoU ≥ 0.5, each used once.
fn count_matched(reference: &[Detection], candidate: &[Detection]) -> usize {
    let mut used = vec![false; candidate.len()];
    reference
        .iter()
        .filter(|r| {
            let best = candidate.iter().enumerate().filter(|(j, c)| !used[*j] && c.class == r.class && iou(&c.bbox, &r.bbox) >= 0.5).max_by(|a, b| iou(&a.1.bbox, &r.bbox).total_cmp(&iou(&b.1.bbox, &r.bbox)));
            best.map(|(j, _)| used[j] = true).is_some()
        })
        .count()
}

impl ConvertReport {
    pub fn render(&self) -> String {
        let mut s = format!("{} (rknn-toolkit2 {}) in {:.0} s; {}\n", self.rknn, self.toolkit, self.seconds, self.validation);
        s += &format!("  {:<18} {:>9} {:>10} {:>10}\n", "simulator vs ORT", "cosine", "rel L2", "max abs");
        s += &format!("  quantization: {}\n", self.quantization);
        for a in self.outputs.iter().chain(&self.groups) {
            s += &format!("  {:<18} {:>9.5} {:>10.3e} {:>10.3e}\n", a.name, a.error.cosine, a.error.rel_l2, a.error.max_abs);
        }
        if !self.trained_qdq.is_empty() {
            s += &format!("  {:<18} {:>9} {:>10} {:>10}\n", "vs trained QDQ", "cosine", "rel L2", "max abs");
            for a in &self.trained_qdq {
                s += &format!("  {:<18} {:>9.5} {:>10.3e} {:>10.3e}\n", a.name, a.error.cosine, a.error.rel_l2, a.error.max_abs);
            }
        }
        s += &format!("  layers: {} on the NPU ({} of {} asked kept in FP16), {} on the CPU\n", self.npu_layers, self.fp16_layers_built, self.fp16_layers.len(), self.cpu_layers.len());
        s += &format!("  detections (conf {}): ORT {}, simulator {}, matched {}\n", self.score_threshold, self.detections_ort, self.detections_rknn, self.detections_matched);
        let flat: Vec<&str> = self.outputs.iter().chain(&self.groups).filter(|a| !(a.error.cosine >= self.min_cosine) && a.error.max_abs < OUTPUT_STEP).map(|a| a.name.as_str()).collect();
        if !flat.is_empty() {
            s += &format!("  within one output step (1/255) everywhere, no signal for cosine: {}\n", flat.join(", "));
        }
        s += &if self.passed { format!("  PASS (every cosine ≥ {} or within one output step, nothing on the CPU)\n", self.min_cosine) } else { format!("  FAIL: {}\n", self.failures.join("; ")) };
        s
    }
}
