//! `pdi-compile stress`: candidates against their reference under the conditions where
//! deployments break (noise, drift, saturation, bad pixels, a drifting blur map, NaN).
//!
//! Every condition transforms the same base frames (seeded, so each candidate sees the same
//! stressed frames as the reference). Per condition and candidate: rel L2 per output group
//! of the detection output (over the values finite in the reference), mAP agreement with
//! the reference's detections on the stressed frames, non-finite outputs, and for INT8 and
//! FP16 candidates what each layer saw (`probes`). Written: stress.json, stress.md and a
//! heatmap (SVG, PNG); a gate turns it into pass/fail.

pub mod gate;
pub mod probes;
pub mod render;

use crate::analysis::head::HeadKind;
use crate::detect::{decode, Detection};
use crate::frames::Frame;
use crate::metrics::coco_map::coco_map;
use crate::metrics::tensor_error::ErrorSums;
use crate::optics::blur_map::BlurMap;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use crate::verify::gate::Check;
use crate::metrics::validation::{agreement_truth, detections};
use crate::verify::{feeds, side, Side};
use anyhow::{anyhow, bail, Result};
use crate::optics::conditions::{self, Condition};
use indicatif::{ProgressBar, ProgressStyle};
use ort::session::builder::GraphOptimizationLevel;
use probes::{LayerStats, Precision, Probe};
use serde::Serialize;
use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

/// Frames per condition when neither the request nor the condition file says.
const DEFAULT_FRAMES: usize = 32;
/// Fewer reference boxes than this make a condition's mAP agreement too coarse to rank
/// (one box moves it by several points): such conditions are reported, never called worst.
pub const MIN_REFERENCE_BOXES: usize = 20;

pub struct StressRequest {
    pub reference: PathBuf,
    pub candidates: Vec<PathBuf>,
    pub psf: Option<PathBuf>,
    pub data: Option<PathBuf>,
    pub conditions: Option<PathBuf>,
    pub frames: Option<usize>,
    pub gate: Option<gate::StressGate>,
    pub seed: u64,
}

#[derive(Serialize)]
pub struct CandidateInfo {
    pub label: String,
    pub path: String,
    pub precision: Precision,
}

/// One candidate under one condition.
#[derive(Clone, Debug, Serialize)]
pub struct Outcome {
    /// rel L2 against the reference per group of the detection output (and "all").
    pub rel_l2: BTreeMap<&'static str, f64>,
    pub worst_rel_l2: f64,
    /// mAP@.5:.95 of the candidate's detections against the reference's; None when the
    /// reference detects nothing on these frames.
    pub agreement: Option<f64>,
    pub agreement50: Option<f64>,
    /// The candidate's detections scoring at least 0.25 (a deployment's usual cut): what it
    /// reports where the reference sees nothing.
    pub boxes: usize,
    /// Detection-output values NaN or infinite in the candidate (`extra_nonfinite`: where
    /// the reference's are finite).
    pub nonfinite: usize,
    pub extra_nonfinite: usize,
    pub values: usize,
    /// INT8 saturation or FP16 headroom per layer.
    pub layers: Option<LayerStats>,
}

#[derive(Serialize)]
pub struct ConditionReport {
    pub name: String,
    pub params: serde_json::Value,
    /// Why the condition was not run (it changes nothing any model here sees).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub skipped: Option<String>,
    pub seconds: f64,
    pub reference_boxes: usize,
    pub reference_nonfinite: usize,
    pub truth: String,
    pub candidates: BTreeMap<String, Outcome>,
}

/// Each candidate's clean agreement and its worst condition (among those with at least
/// MIN_REFERENCE_BOXES reference boxes).
#[derive(Serialize)]
pub struct Summary {
    pub candidate: String,
    pub clean: Option<f64>,
    pub worst_condition: Option<String>,
    pub worst_agreement: Option<f64>,
}

#[derive(Serialize)]
pub struct StressReport {
    pub reference: String,
    pub candidates: Vec<CandidateInfo>,
    pub frames: usize,
    pub frame_source: String,
    pub condition_source: String,
    pub threads: usize,
    pub seconds: f64,
    pub conditions: Vec<ConditionReport>,
    pub summary: Vec<Summary>,
    pub checks: Vec<Check>,
    pub passed: bool,
}

struct Candidate {
    label: String,
    side: Side,
    rt: OrtRuntime,
    probe: Option<Probe>,
}

/// Running figures of one candidate under one condition.
#[derive(Default)]
struct Tally {
    groups: BTreeMap<&'static str, ErrorSums>,
    dets: Vec<Vec<Detection>>,
    nonfinite: usize,
    extra_nonfinite: usize,
    values: usize,
}

pub fn stress(req: &StressRequest) -> Result<StressReport> {
    let started = Instant::now();
    if req.candidates.is_empty() {
        bail!("stress needs at least one --candidate (a compiled model.onnx)");
    }
    let set = conditions::load(req.conditions.as_deref())?;
    if let Some(g) = &req.gate {
        g.validate(&set.conditions.iter().map(|c| c.name.clone()).collect::<Vec<_>>())?;
    }
    let reference = side(&req.reference, "reference")?;
    let head = crate::inspect::inspect(&reference.model)?.head;
    let det = match (&head.kind, &head.output) {
        (HeadKind::Yolov5Anchor | HeadKind::Yolov8Dfl, Some(o)) => o.clone(),
        _ => bail!("the reference {} has no decodable detection output (YOLOv5 or YOLOv8 head); stress compares detections", req.reference.display()),
    };
    let classes = head.classes.unwrap_or(1).max(1);
    let (h, w) = reference.input.shape;
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());

    let mut cands = Vec::new();
    for path in &req.candidates {
        let s = side(path, "candidate")?;
        if crate::scene::compare::SceneView::new(&s.model, head.kind, classes, reference.input.shape)?.is_some() {
            bail!("{} is scene-specialized; stress compares full-frame candidates (check it with verify)", path.display());
        }
        if s.input.shape != reference.input.shape {
            bail!("{} takes {:?} frames, the reference {:?}", path.display(), s.input.shape, reference.input.shape);
        }
        if !s.model.graph.as_ref().is_some_and(|g| g.output.iter().any(|o| o.name == det)) {
            bail!("{} has no output '{det}' (the reference's detection output)", path.display());
        }
        let rt = OrtRuntime::with_options(&s.model, GraphOptimizationLevel::Level3, threads)?;
        let probe = Probe::new(&s.model, threads)?;
        cands.push(Candidate { label: label(path, &cands), side: s, rt, probe });
    }
    let infos: Vec<CandidateInfo> = cands.iter().zip(&req.candidates).map(|(c, p)| CandidateInfo { label: c.label.clone(), path: p.display().to_string(), precision: probes::precision(&c.side.model) }).collect();

    let n = req.frames.or(set.frames).unwrap_or(DEFAULT_FRAMES);
    let (base, frame_source) = match &req.data {
        Some(d) => {
            let mut f = crate::frames::load_folder(d, h, w)?;
            f.truncate(n);
            let source = format!("{} frames from {}", f.len(), d.display());
            (f, source)
        }
        None => {
            let s = crate::calib_frames::calibration_frames(None, n, h, w, req.seed)?;
            (s.frames, s.source)
        }
    };
    let base_map = req.psf.as_deref().map(BlurMap::load).transpose()?;
    let takes_blur = !reference.input.other_inputs.is_empty() || cands.iter().any(|c| !c.side.input.other_inputs.is_empty());
    let mut ref_rt = OrtRuntime::with_options(&reference.model, GraphOptimizationLevel::Level3, threads)?;

    let pb = ProgressBar::new((set.conditions.len() * base.len()) as u64);
    pb.set_style(ProgressStyle::with_template("stress {msg:<22} [{bar:30}] {pos}/{len} frames ({elapsed})").expect("valid template").progress_chars("=> "));
    let mut reports = Vec::new();
    for (ci, cond) in set.conditions.iter().enumerate() {
        pb.set_message(cond.name.clone());
        let t = Instant::now();
        let params = serde_json::to_value(&cond.kind)?;
        if cond.changes_blur() && !takes_blur {
            crate::warn::warn(format!("stress: '{}' changes the blur map, and neither the reference nor a candidate takes one as an input; skipped", cond.name));
            pb.inc(base.len() as u64);
            reports.push(ConditionReport { name: cond.name.clone(), params, skipped: Some("no model here takes the blur map as an input".into()), seconds: 0.0, reference_boxes: 0, reference_nonfinite: 0, truth: String::new(), candidates: BTreeMap::new() });
            continue;
        }
        let map = base_map.as_ref().map(|m| {
            let m = cond.blur_map(m);
            Tensor::f32(vec![1, 1, m.rows, m.cols], m.values)
        });
        let mut tallies: Vec<Tally> = cands.iter().map(|_| Tally::default()).collect();
        let (mut ref_dets, mut ref_nonfinite) = (Vec::new(), 0usize);
        for (k, f) in base.iter().enumerate() {
            let frame = stressed(cond, f, req.seed ^ ((ci as u64) << 32 | k as u64));
            let r = ref_rt.run(&feeds(&reference, &frame, map.as_ref())?)?;
            let rt = output(&r, &det)?;
            ref_nonfinite += rt.data.to_f64().iter().filter(|v| !v.is_finite()).count();
            ref_dets.push(detections(&head, &r)?);
            for (c, tally) in cands.iter_mut().zip(&mut tallies) {
                let fc = feeds(&c.side, &frame, map.as_ref())?;
                let out = c.rt.run(&fc)?;
                if let Some(p) = c.probe.as_mut() {
                    p.observe(&fc)?;
                }
                tally.add(head.kind, rt, output(&out, &det)?)?;
                tally.dets.push(detections(&head, &out)?);
            }
            pb.inc(1);
        }
        let (truth, how) = agreement_truth(&ref_dets, classes);
        let boxes: usize = truth.iter().map(Vec::len).sum();
        let mut outcomes = BTreeMap::new();
        for (c, tally) in cands.iter_mut().zip(tallies) {
            let map = (boxes > 0).then(|| coco_map(&truth, &tally.dets, classes));
            let rel_l2: BTreeMap<&'static str, f64> = tally.groups.iter().map(|(g, s)| (*g, s.finish().rel_l2)).collect();
            let worst_rel_l2 = rel_l2.iter().filter(|(g, _)| **g != "all").map(|(_, v)| *v).fold(0.0, f64::max);
            outcomes.insert(
                c.label.clone(),
                Outcome {
                    rel_l2,
                    worst_rel_l2,
                    agreement: map.as_ref().map(|m| m.map50_95),
                    agreement50: map.as_ref().map(|m| m.map50),
                    boxes: tally.dets.iter().flatten().filter(|d| d.score >= crate::metrics::validation::AGREEMENT_CONF).count(),
                    nonfinite: tally.nonfinite,
                    extra_nonfinite: tally.extra_nonfinite,
                    values: tally.values,
                    layers: c.probe.as_mut().map(Probe::take),
                },
            );
        }
        reports.push(ConditionReport { name: cond.name.clone(), params, skipped: None, seconds: t.elapsed().as_secs_f64(), reference_boxes: boxes, reference_nonfinite: ref_nonfinite, truth: how, candidates: outcomes });
    }
    pb.finish_and_clear();
    let checks = req.gate.as_ref().map(|g| g.checks(&reports)).unwrap_or_default();
    let summary = cands.iter().map(|c| summarize(&c.label, &reports)).collect();
    Ok(StressReport {
        reference: req.reference.display().to_string(),
        candidates: infos,
        frames: base.len(),
        frame_source,
        condition_source: set.source,
        threads,
        seconds: started.elapsed().as_secs_f64(),
        passed: checks.iter().all(|c| c.passed),
        checks,
        conditions: reports,
        summary,
    })
}

fn summarize(cand: &str, reports: &[ConditionReport]) -> Summary {
    let clean = reports.iter().find(|c| c.name == "clean").and_then(|c| c.candidates.get(cand)?.agreement);
    let worst = reports
        .iter()
        .filter(|c| c.reference_boxes >= MIN_REFERENCE_BOXES)
        .filter_map(|c| Some((c.name.clone(), c.candidates.get(cand)?.agreement?)))
        .min_by(|a, b| a.1.total_cmp(&b.1));
    Summary { candidate: cand.to_string(), clean, worst_agreement: worst.as_ref().map(|w| w.1), worst_condition: worst.map(|w| w.0) }
}

/// `f` under `cond`, seeded per condition and frame.
fn stressed(cond: &Condition, f: &Frame, seed: u64) -> Frame {
    Frame { name: f.name.clone(), image: cond.apply_tensor(&f.image, seed), labels: None }
}

fn output<'a>(outs: &'a [(String, Tensor)], name: &str) -> Result<&'a Tensor> {
    outs.iter().find(|(n, _)| n == name).map(|(_, t)| t).ok_or_else(|| anyhow!("output {name} missing"))
}

/// A short unique label: the file stem, or its folder's name for a compile's `model.onnx`.
fn label(path: &std::path::Path, taken: &[Candidate]) -> String {
    let stem = path.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let base = if stem == "model" { path.parent().and_then(|p| p.file_name()).map_or(stem, |s| s.to_string_lossy().into_owned()) } else { stem };
    let mut name = base.clone();
    let mut k = 2;
    while taken.iter().any(|c| c.label == name) {
        name = format!("{base}_{k}");
        k += 1;
    }
    name
}

impl Tally {
    fn add(&mut self, kind: HeadKind, reference: &Tensor, candidate: &Tensor) -> Result<()> {
        if reference.shape != candidate.shape {
            bail!("detection output: reference shape {:?}, candidate {:?}", reference.shape, candidate.shape);
        }
        let (r, c) = (reference.data.to_f64(), candidate.data.to_f64());
        self.values += c.len();
        self.nonfinite += c.iter().filter(|v| !v.is_finite()).count();
        self.extra_nonfinite += r.iter().zip(&c).filter(|(a, b)| a.is_finite() && !b.is_finite()).count();
        // Where the reference itself is not finite there is nothing to be close to.
        let finite = |a: &[f64], b: &[f64]| -> (Vec<f64>, Vec<f64>) { a.iter().zip(b).filter(|(x, _)| x.is_finite()).map(|(x, y)| (*x, *y)).unzip() };
        let (fr, fc) = finite(&r, &c);
        self.groups.entry("all").or_default().add(fr.into_iter(), fc.into_iter());
        for (g, range) in decode::channel_groups(kind, &reference.shape) {
            let (a, b) = (crate::metrics::validation::select_channels(kind, reference, range.clone()), crate::metrics::validation::select_channels(kind, candidate, range));
            let (fa, fb) = finite(&a, &b);
            self.groups.entry(g).or_default().add(fa.into_iter(), fb.into_iter());
        }
        Ok(())
    }
}
