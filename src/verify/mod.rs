//! `pdi-compile verify`: a candidate against its reference, on the same frames.
//!
//! The reference runs on ONNX Runtime; the candidate on ONNX Runtime and on tract. Reported:
//! per output max abs / rel L2 / cosine (detection outputs also per channel group, boxes
//! apart from scores), detections decoded and compared as COCO mAP (the candidate's against
//! the reference's detections, and both against labels when frames have them), and latency
//! measured interleaved. A gate turns the report into pass/fail.

pub mod gate;
pub mod junit;

use crate::analysis::head::{Head, HeadKind};
use crate::metrics::validation::{agreement_truth, detections, select_channels, AGREEMENT_CONF};
use crate::deploy::input::ModelInput;
use crate::detect::{decode, Detection};
use crate::frames::{self, Frame};
use crate::metrics::coco_map::{coco_map, MapResult, Truth};
use crate::metrics::tensor_error::{compare, TensorError};
use crate::onnx::proto::ModelProto;
use crate::runtime::{self, latency, Engine, Runtime};
use crate::scene::compare::SceneView;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use gate::{Check, Gate};
use serde::Serialize;
use std::path::PathBuf;

pub struct VerifyRequest {
    pub reference: PathBuf,
    pub candidate: PathBuf,
    pub data: Option<PathBuf>,
    pub random: usize,
    pub psf: Option<PathBuf>,
    pub gate: Option<Gate>,
    /// Timed runs per model; 0 measures accuracy only (bench times all variants together).
    pub latency_runs: usize,
    pub tract: bool,
    pub seed: u64,
    /// Threads of every session, ORT and tract alike, so their latencies compare.
    pub threads: usize,
}

#[derive(Serialize)]
pub struct GroupError {
    pub group: &'static str,
    pub ort: TensorError,
}

#[derive(Serialize)]
pub struct OutputReport {
    pub name: String,
    /// Candidate on ORT vs reference on ORT.
    pub ort: TensorError,
    /// Candidate on tract vs candidate on ORT.
    pub tract: Option<TensorError>,
    /// Candidate on tract vs reference on ORT (what a tract deployment loses in all).
    pub tract_vs_reference: Option<TensorError>,
    pub groups: Vec<GroupError>,
}

#[derive(Serialize)]
pub struct DetectionReport {
    pub head: Head,
    /// How the reference's detections used as truth were chosen.
    pub truth: String,
    pub truth_boxes: usize,
    /// Candidate (ORT) detections scored against the reference's.
    pub agreement: MapResult,
    pub agreement_tract: Option<MapResult>,
    /// Against the frames' labels, when every frame has them.
    pub reference_vs_labels: Option<MapResult>,
    pub candidate_vs_labels: Option<MapResult>,
    /// For a scene-specialized candidate: what was compared.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub scene: Option<String>,
    /// For a scene-specialized candidate: whether its detections scoring at least
    /// AGREEMENT_CONF are the reference's (restricted to the scene), bit for bit.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub identical: Option<bool>,
}

#[derive(Serialize)]
pub struct VerifyReport {
    pub reference: String,
    pub candidate: String,
    pub frames: usize,
    pub frame_source: String,
    /// The candidate is the reference's model: its outputs were the reference's, run once.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub candidate_is_reference: bool,
    pub outputs: Vec<OutputReport>,
    pub detection: Option<DetectionReport>,
    pub latency: Vec<latency::Latency>,
    /// Candidate / reference median on ORT (None when latency was not measured).
    pub latency_ratio: Option<f64>,
    /// Candidate on tract / candidate on ORT, same threads, same loop.
    pub tract_vs_ort_ratio: Option<f64>,
    pub threads: usize,
    pub checks: Vec<Check>,
    pub passed: bool,
}

/// A model to compare and what it takes.
pub(crate) struct Side {
    pub(crate) model: ModelProto,
    pub(crate) input: ModelInput,
}

pub(crate) fn side(path: &std::path::Path, what: &str) -> Result<Side> {
    let model = crate::onnx::load(path)?.model;
    let input = ModelInput::of(&model, &format!("{what} {}", path.display()))?;
    Ok(Side { model, input })
}

pub(crate) use crate::deploy::input::blur_input;

pub(crate) fn feeds(side: &Side, frame: &Frame, psf: Option<&Tensor>) -> Result<Vec<(String, Tensor)>> {
    let mut v = vec![(side.input.image_input.clone(), crate::calib_frames::replicate(&frame.image, side.input.channels))];
    for n in &side.input.other_inputs {
        let p = psf.ok_or_else(|| anyhow!("input '{n}' needs a value: give the camera's blur map with --psf"))?;
        v.push((n.clone(), p.clone()));
    }
    Ok(v)
}


pub fn verify(req: &VerifyRequest) -> Result<VerifyReport> {
    // Without timed runs a latency gate is unmeasured: refused, unless the command says it may
    // go unmeasured (accuracy gates on a shared CI runner, where latency is noise).
    if req.latency_runs == 0 && req.gate.as_ref().is_some_and(|g| g.max_latency_ratio.is_some() && !g.allow_unmeasured.iter().any(|k| k == "max_latency_ratio")) {
        bail!("the gate checks max_latency_ratio, which needs timed runs: give --runs 1 or more, or --allow-unmeasured max_latency_ratio");
    }
    let reference = side(&req.reference, "reference")?;
    let candidate = side(&req.candidate, "candidate")?;
    // Before the scene view, which reads the candidate's detection output.
    let cand_outputs: Vec<String> = candidate.model.graph.as_ref().unwrap().output.iter().map(|o| o.name.clone()).collect();
    let compared: Vec<String> = reference.model.graph.as_ref().unwrap().output.iter().map(|o| o.name.clone()).filter(|n| cand_outputs.contains(n)).collect();
    if compared.is_empty() {
        bail!("the candidate shares no output name with the reference; nothing to compare (a split head from rknn-legalize is checked by rknn-convert, or verify the model compiled without rknn-legalize)");
    }
    let head = crate::inspect::inspect(&reference.model)?.head;
    let scene = SceneView::new(&candidate.model, head.kind, head.classes.unwrap_or(0), reference.input.shape)?;
    if scene.is_none() && reference.input.shape != candidate.input.shape {
        bail!("reference takes {:?} frames, candidate {:?}", reference.input.shape, candidate.input.shape);
    }
    let (h, w) = reference.input.shape;
    let (frames, frame_source) = match &req.data {
        Some(d) => (frames::load_folder(d, h, w)?, d.display().to_string()),
        None => (frames::synthetic(req.random.max(1), h, w, req.seed), format!("{} synthetic frames, seed {}", req.random.max(1), req.seed)),
    };
    let psf = req.psf.as_deref().map(blur_input).transpose()?;
    // A specialized candidate decodes its own classes; its detections are compared on the scene.
    let cand_head = match &scene {
        Some(_) => crate::inspect::inspect(&candidate.model)?.head,
        None => head.clone(),
    };
    let crop = |f: &Frame| -> Result<Frame> { scene.as_ref().map_or(Ok(f.clone()), |s| s.crop(f)) };

    let first_ref = feeds(&reference, &frames[0], psf.as_ref())?;
    let first_cand = feeds(&candidate, &crop(&frames[0])?, psf.as_ref())?;
    let mut ref_rt = runtime::load(Engine::Ort, &reference.model, &first_ref, req.threads)?;
    // A model verified against itself (a card's mAP against labels) runs once per frame on
    // ONNX Runtime: the candidate's outputs are the reference's, which the same session on
    // the same feeds would give again. Timed runs still time both sessions. The models are
    // compared as loaded above, not read again.
    let same = scene.is_none() && reference.model == candidate.model;
    let mut cand_rt = if same && req.latency_runs == 0 { None } else { Some(runtime::load(Engine::Ort, &candidate.model, &first_cand, req.threads)?) };
    let mut tract_rt = if req.tract { Some(runtime::load(Engine::Tract, &candidate.model, &first_cand, req.threads)?) } else { None };

    let n_out = compared.len();
    let (mut ref_vals, mut cand_vals, mut tract_vals) = (vec![Vec::new(); n_out], vec![Vec::new(); n_out], vec![Vec::new(); n_out]);
    let mut shapes = vec![Vec::new(); n_out];
    let (mut ref_dets, mut cand_dets, mut tract_dets) = (Vec::new(), Vec::new(), Vec::new());
    let decodable = head.kind != HeadKind::Raw && head.output.as_ref().is_some_and(|o| compared.contains(o));
    for f in &frames {
        let full = ref_rt.run(&feeds(&reference, f, psf.as_ref())?)?;
        let r = match (&scene, &head.output) {
            (Some(s), Some(det)) => full.iter().map(|(n, t)| Ok((n.clone(), if n == det { s.gather(t)? } else { t.clone() }))).collect::<Result<Vec<_>>>()?,
            _ => full.clone(),
        };
        let cf = feeds(&candidate, &crop(f)?, psf.as_ref())?;
        let c = match cand_rt.as_mut() {
            Some(rt) if !same => rt.run(&cf)?,
            _ => r.clone(),
        };
        let t = tract_rt.as_mut().map(|rt| rt.run(&cf)).transpose()?;
        for (k, name) in compared.iter().enumerate() {
            let get = |outs: &[(String, Tensor)]| outs.iter().find(|(n, _)| n == name).map(|(_, t)| t.clone()).ok_or_else(|| anyhow!("output {name} missing"));
            let (rt_, ct) = (get(&r)?, get(&c)?);
            if rt_.shape != ct.shape {
                bail!("output {name}: reference shape {:?}, candidate {:?}", rt_.shape, ct.shape);
            }
            shapes[k] = rt_.shape.clone();
            ref_vals[k].push(rt_);
            cand_vals[k].push(ct);
            if let Some(t) = &t {
                tract_vals[k].push(get(t)?);
            }
        }
        if decodable {
            match &scene {
                Some(s) => {
                    let det = head.output.as_deref().unwrap_or_default();
                    let restricted: Vec<(String, Tensor)> = full.iter().map(|(n, t)| Ok((n.clone(), if n == det { s.kept_classes(t)? } else { t.clone() }))).collect::<Result<_>>()?;
                    ref_dets.push(s.reference_detections(detections(&head, &restricted)?));
                    cand_dets.push(s.candidate_detections(detections(&cand_head, &c)?));
                    if let Some(t) = &t {
                        tract_dets.push(s.candidate_detections(detections(&cand_head, t)?));
                    }
                }
                None => {
                    ref_dets.push(detections(&head, &r)?);
                    cand_dets.push(detections(&head, &c)?);
                    if let Some(t) = &t {
                        tract_dets.push(detections(&head, t)?);
                    }
                }
            }
        }
    }

    let flat = |ts: &[Tensor]| -> Vec<f64> { ts.iter().flat_map(|t| t.data.to_f64()).collect() };
    let mut outputs = Vec::new();
    for (k, name) in compared.iter().enumerate() {
        let (r, c) = (flat(&ref_vals[k]), flat(&cand_vals[k]));
        let groups = if Some(name) == head.output.as_ref() {
            decode::channel_groups(head.kind, &shapes[k])
                .into_iter()
                .map(|(g, range)| {
                    let pick = |ts: &[Tensor]| -> Vec<f64> { ts.iter().flat_map(|t| select_channels(head.kind, t, range.clone())).collect() };
                    GroupError { group: g, ort: compare(&pick(&ref_vals[k]), &pick(&cand_vals[k])) }
                })
                .collect()
        } else {
            Vec::new()
        };
        let t = (!tract_vals[k].is_empty()).then(|| flat(&tract_vals[k]));
        let (tract, tract_vs_reference) = (t.as_ref().map(|t| compare(&c, t)), t.as_ref().map(|t| compare(&r, t)));
        outputs.push(OutputReport { name: name.clone(), ort: compare(&r, &c), tract, tract_vs_reference, groups });
    }

    let detection = match &scene {
        None => decodable.then(|| detection_report(&head, &frames, &ref_dets, &cand_dets, &tract_dets)),
        Some(s) => decodable.then(|| {
            let scene_frames: Vec<Frame> = frames.iter().map(|f| Frame { labels: f.labels.as_ref().map(|l| s.labels(l)), ..f.clone() }).collect();
            let mut d = detection_report(&cand_head, &scene_frames, &ref_dets, &cand_dets, &tract_dets);
            d.scene = Some(s.describe());
            d.identical = Some(same_detections(&ref_dets, &cand_dets));
            d
        }),
    };

    let latency = if req.latency_runs == 0 {
        Vec::new()
    } else {
        let Some(cand_rt) = cand_rt.as_mut() else { bail!("timed runs need the candidate's session") };
        let mut models: Vec<(String, &mut dyn Runtime, Vec<(String, Tensor)>)> = vec![("reference/ort".into(), ref_rt.as_mut(), first_ref), ("candidate/ort".into(), cand_rt.as_mut(), first_cand.clone())];
        if let Some(t) = tract_rt.as_mut() {
            models.push(("candidate/tract".into(), t.as_mut(), first_cand));
        }
        latency::interleaved(&mut models, req.latency_runs)?
    };
    let latency_ratio = (latency.len() >= 2).then(|| latency[1].median_ms / latency[0].median_ms);
    let tract_vs_ort_ratio = (latency.len() >= 3).then(|| latency[2].median_ms / latency[1].median_ms);

    let mut checks = Vec::new();
    if let Some(g) = &req.gate {
        checks = self::checks(g, &outputs, detection.as_ref(), latency_ratio, req.tract);
        gate::allow_unmeasured(&mut checks, &g.allow_unmeasured, gate::KEYS)?;
    }
    let passed = checks.iter().all(|c| c.passed);
    Ok(VerifyReport {
        reference: req.reference.display().to_string(),
        candidate: req.candidate.display().to_string(),
        frames: frames.len(),
        frame_source,
        candidate_is_reference: same,
        outputs,
        detection,
        latency,
        latency_ratio,
        tract_vs_ort_ratio,
        threads: req.threads,
        checks,
        passed,
    })
}



fn detection_report(head: &Head, frames: &[Frame], reference: &[Vec<Detection>], candidate: &[Vec<Detection>], tract: &[Vec<Detection>]) -> DetectionReport {
    let classes = head.classes.unwrap_or(1).max(1);
    let (truth, how) = agreement_truth(reference, classes);
    let labels: Option<Vec<Vec<Truth>>> = frames.iter().map(|f| f.labels.clone()).collect();
    DetectionReport {
        head: head.clone(),
        truth: how,
        truth_boxes: truth.iter().map(Vec::len).sum(),
        agreement: coco_map(&truth, candidate, classes),
        agreement_tract: (!tract.is_empty()).then(|| coco_map(&truth, tract, classes)),
        reference_vs_labels: labels.as_ref().map(|l| coco_map(l, reference, classes)),
        candidate_vs_labels: labels.as_ref().map(|l| coco_map(l, candidate, classes)),
        scene: None,
        identical: None,
    }
}

/// Whether two runs kept the same confident detections, bit for bit.
fn same_detections(a: &[Vec<Detection>], b: &[Vec<Detection>]) -> bool {
    let confident = |ds: &Vec<Detection>| -> Vec<Detection> { ds.iter().filter(|d| d.score >= AGREEMENT_CONF).copied().collect() };
    a.len() == b.len() && a.iter().zip(b).all(|(x, y)| confident(x) == confident(y))
}

fn checks(g: &Gate, outputs: &[OutputReport], det: Option<&DetectionReport>, latency_ratio: Option<f64>, tract_ran: bool) -> Vec<Check> {
    let mut c = Vec::new();
    for o in outputs {
        if let Some(t) = g.max_rel_l2 {
            c.push(Check::max("max_rel_l2", format!("{}: rel L2 (ort)", o.name), o.ort.rel_l2, t));
        }
        if let Some(t) = g.min_cosine {
            c.push(Check::min("min_cosine", format!("{}: cosine (ort)", o.name), o.ort.cosine, t));
        }
        match (g.max_rel_l2_tract, o.tract) {
            (Some(t), Some(e)) => c.push(Check::max("max_rel_l2_tract", format!("{}: rel L2 (tract vs ort)", o.name), e.rel_l2, t)),
            (Some(t), None) => {
                let why = if tract_ran { "tract did not produce this output" } else { "tract was not run (--no-tract)" };
                c.push(Check::unmeasured("max_rel_l2_tract", format!("{}: rel L2 (tract vs ort)", o.name), "max", t, why));
            }
            _ => {}
        }
    }
    let agreement = "mAP@.5:.95 agreement with the reference";
    let drop = "mAP@.5:.95 drop against labels";
    match det {
        Some(d) => {
            if let Some(t) = g.min_map_agreement {
                c.push(Check::min("min_map_agreement", agreement, d.agreement.map50_95, t));
            }
            match (g.max_map_drop, &d.reference_vs_labels, &d.candidate_vs_labels) {
                (Some(t), Some(r), Some(k)) => c.push(Check::max("max_map_drop", drop, r.map50_95 - k.map50_95, t)),
                (Some(t), _, _) => c.push(Check::unmeasured("max_map_drop", drop, "max", t, "the frames have no labels (give --data a folder with YOLO .txt labels beside its frames)")),
                _ => {}
            }
        }
        None => {
            let why = "the reference has no decoded detection output to score";
            if let Some(t) = g.min_map_agreement {
                c.push(Check::unmeasured("min_map_agreement", agreement, "min", t, why));
            }
            if let Some(t) = g.max_map_drop {
                c.push(Check::unmeasured("max_map_drop", drop, "max", t, why));
            }
        }
    }
    match (g.max_latency_ratio, latency_ratio) {
        (Some(t), Some(r)) => c.push(Check::max("max_latency_ratio", "latency ratio candidate/reference (ort)", r, t)),
        (Some(t), None) => c.push(Check::unmeasured("max_latency_ratio", "latency ratio candidate/reference (ort)", "max", t, "no timed runs")),
        _ => {}
    }
    c
}

impl VerifyReport {
    pub fn render(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let _ = writeln!(s, "verify {} against {} on {} frame(s) ({})", self.candidate, self.reference, self.frames, self.frame_source);
        for o in &self.outputs {
            let _ = writeln!(s, "  {:<14} ort: max abs {:.3e}  rel L2 {:.3e}  cosine {:.8}", o.name, o.ort.max_abs, o.ort.rel_l2, o.ort.cosine);
            for g in &o.groups {
                let _ = writeln!(s, "    {:<12} max abs {:.3e}  rel L2 {:.3e}", g.group, g.ort.max_abs, g.ort.rel_l2);
            }
            if let Some(t) = &o.tract {
                let _ = writeln!(s, "    tract vs ort  max abs {:.3e}  rel L2 {:.3e}", t.max_abs, t.rel_l2);
            }
        }
        if let Some(d) = &self.detection {
            if let Some(scene) = &d.scene {
                let same = match d.identical {
                    Some(true) => "; confident detections identical to the reference's",
                    _ => "",
                };
                let _ = writeln!(s, "  {scene}{same}");
            }
            let _ = writeln!(s, "  detections ({:?}): agreement mAP@.5 {:.4}  mAP@.5:.95 {:.4}  over {} reference boxes ({})", d.head.kind, d.agreement.map50, d.agreement.map50_95, d.truth_boxes, d.truth);
            if let (Some(r), Some(c)) = (&d.reference_vs_labels, &d.candidate_vs_labels) {
                let _ = writeln!(s, "  vs labels: reference mAP@.5 {:.4} mAP@.5:.95 {:.4}; candidate {:.4} / {:.4}", r.map50, r.map50_95, c.map50, c.map50_95);
            }
        }
        for l in &self.latency {
            let _ = writeln!(s, "  latency {:<16} median {:.2} ms (min {:.2}, {} runs)", l.name, l.median_ms, l.min_ms, l.runs);
        }
        if let Some(r) = self.latency_ratio {
            let _ = writeln!(s, "  latency ratio candidate/reference on ORT: {r:.3} ({} threads)", self.threads);
        }
        if let Some(r) = self.tract_vs_ort_ratio {
            let _ = writeln!(s, "  latency ratio candidate tract/ORT: {r:.3}");
        }
        for c in &self.checks {
            let _ = writeln!(s, "  {}", c.line());
        }
        if !self.checks.is_empty() {
            let _ = writeln!(s, "{}", if self.passed { "gate passed" } else { "gate FAILED" });
        }
        s
    }
}
