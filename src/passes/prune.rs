//! `prune`: structured channel pruning with dependency groups, and training-free
//! compensation.
//!
//! Needs: a detection graph with constant weights and one image input (run the lossless
//! passes first: bind-psf, fold-constants, fold-bn). Calibration frames come from
//! `--calib`, or from the physics pipeline when none is given (activation importance and
//! compensation use them; magnitude importance without compensation needs none).
//! With `unused_levels`, detection levels that hold (almost) none of the model's detections
//! on calibration frames go first, as `drop-strides` removes them for a scene, and the
//! budget still counts from the model with every level. `max_ratios` bounds what a target
//! may cut from the groups under a name prefix.
//! Guarantees: outputs keep their names and shapes; the image input, the detection head's
//! output convolutions, graph outputs and `ignore` keep every channel; a group the channel
//! analysis cannot see through is left whole and named, never pruned wrongly; compensation
//! is kept only when it lowers the worst output group's rel L2 (boxes, objectness, classes
//! apart) on held-out calibration frames, otherwise the plain pruned weights are emitted.
//! Reports: every group with channels before/after (and why it was kept or how it was
//! rounded), MACs and parameters before/after, compensation work (and whether it was kept),
//! and the rel L2 per output and channel group against the unpruned model on held-out
//! calibration frames, without and with compensation.

use crate::analysis::channels::analyse;
use crate::calib_frames::image_feeds;
use crate::ir::{infer, Graph};
use crate::quant::attribution::{worst_rel_l2, OutputError, ReferenceOutputs};
use crate::onnx::edit::expose_outputs;
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use crate::clock::Clock;
use crate::inspect::counts;
use crate::prune::compensate::{self, Mode};
use crate::prune::importance::{self, Criterion};
use crate::prune::sensitivity::{allocate as allocate_ratios, Budget, GroupSensitivity, Level, LEVELS};
use crate::prune::{apply, select, Scope, SelectOptions};
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::scene::levels::{detection_shares, drop_levels, Measure};
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use std::collections::HashMap;

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// Fraction of each group's channels removed.
    pub ratio: f64,
    /// How channels are ranked: `l1` or `l2` norm of their weights, `bn_gamma` (|gamma| of their
    /// BatchNorm; L1 where there is none), `activation` (mean |activation| on calibration frames).
    pub importance: Criterion,
    /// `uniform`: the same ratio in every group; `global`: one threshold on group-normalized
    /// importance across the model. Ignored with `target`.
    pub scope: Scope,
    /// Kept channel counts are multiples of this where a group has at least twice as many (16:
    /// ONNX Runtime's blocks on AVX-512 and the RK3588's alignment; 8: AVX2's lanes).
    pub round_to: usize,
    /// What repairs the layers after a cut: `none`, `bias` (mean-shift of the biases), `lstsq`
    /// (ridge refit of the next dense convolution, then the mean shift).
    pub compensate: Mode,
    /// Calibration frames used (from `--calib` or simulated); every 4th is held out to
    /// measure the result.
    pub calib_frames: usize,
    /// Ridge strength of the refit, relative to the mean input variance.
    pub ridge: f64,
    /// Values or node names whose channels must all stay.
    pub ignore: Vec<String>,
    /// Seed of the simulated calibration frames (when no `--calib`).
    pub seed: u64,
    /// A budget instead of one ratio: per-group ratios from measured sensitivity.
    pub target: Option<Target>,
    /// Calibration frames the sensitivity of each group is measured on.
    pub sensitivity_frames: usize,
    /// Per-group ratios given outright (group anchor -> ratio; groups not named stay whole),
    /// instead of `ratio` or `target`: what `rebuild` puts in place of a latency target, the
    /// ratios the timed build chose, so that the rebuild does not time again.
    pub ratios: Option<std::collections::BTreeMap<String, f64>>,
    /// Detection levels (strides) holding at most this share of the model's detections on
    /// calibration frames (score 0.25 and above, after one NMS over all levels, any size) go
    /// before any channel, with the neck and head nodes only they feed. A YOLOv8 trained on
    /// small objects can assign every object to its finest level; its coarser levels then
    /// cost MACs and budget for nothing. A MAC or latency target still counts from the model
    /// with all its levels, so what they cost is spent on the levels that detect. None: every
    /// level stays.
    pub unused_levels: Option<f64>,
    /// The largest ratio a `target`'s allocation may give the groups whose anchor starts with
    /// a prefix (prefix -> ratio; the longest matching prefix counts). The allocation reads
    /// each cut's damage before recovery; a YOLOv8 box branch's loss shows after it, at high
    /// IoU, where its boxes' last fraction of a pixel needs the width.
    pub max_ratios: std::collections::BTreeMap<String, f64>,
}

/// What sensitivity-guided pruning must reach, as a fraction of the unpruned model: one of
/// the two.
#[derive(serde::Deserialize, serde::Serialize, Clone, Copy, Debug)]
#[serde(deny_unknown_fields)]
pub struct Target {
    /// MACs of the pruned model over the unpruned one.
    pub macs: Option<f64>,
    /// ONNX Runtime latency over the unpruned model's, measured interleaved on this machine.
    pub latency: Option<f64>,
}

impl Default for Options {
    fn default() -> Self {
        Options { ratio: 0.5, importance: Criterion::L1, scope: Scope::Uniform, round_to: 8, compensate: Mode::Lstsq, calib_frames: 12, ridge: 1e-3, ignore: Vec::new(), seed: 0, target: None, sensitivity_frames: 4, ratios: None, unused_levels: None, max_ratios: Default::default() }
    }
}

pub struct Prune {
    pub options: Options,
}

/// Pixel positions per frame entering a regression: enough to pin down a few hundred
/// coefficients, few enough that the Gram matrix stays cheap at 640x480.
const MAX_REGRESSION_POSITIONS: usize = 8192;
/// Pixels of calibration frames compensation fits on (4 frames at 640x480, 21 at 256x192).
const COMPENSATION_PIXELS: usize = 1 << 20;
/// Calibration frames the levels' shares are measured on (`drop-strides`' default: 128
/// synthetic frames at 256x192 hold over a hundred detections).
const LEVEL_FRAMES: usize = 128;
/// Score at which a detection counts in that measurement (YOLO's deployment default).
const LEVEL_SCORE: f32 = 0.25;

impl Pass for Prune {
    fn name(&self) -> &'static str {
        "prune"
    }

    fn provides(&self) -> Vec<super::Capability> {
        vec![super::Capability::Teacher]
    }

    fn check(&self) -> Result<()> {
        let o = &self.options;
        if !(0.0..1.0).contains(&o.ratio) {
            bail!("prune ratio {} must be in [0, 1)", o.ratio);
        }
        if let Some((g, r)) = o.ratios.iter().flatten().find(|(_, r)| !(0.0..1.0).contains(*r)) {
            bail!("prune ratios: {g}'s {r} must be in [0, 1)");
        }
        if let Some((g, r)) = o.max_ratios.iter().find(|(_, r)| !(0.0..1.0).contains(*r)) {
            bail!("prune max_ratios: {g}'s {r} must be in [0, 1)");
        }
        if !o.max_ratios.is_empty() && o.target.is_none() {
            bail!("prune max_ratios bounds what a target allocates: give a target, e.g. target: {{macs: 0.3}}");
        }
        if o.target.is_some() && o.ratios.is_some() {
            bail!("prune takes a target or ratios, not both");
        }
        if let Some(s) = o.unused_levels.filter(|s| !(0.0..1.0).contains(s)) {
            bail!("prune unused_levels {s} must be a share in [0, 1) of the model's detections");
        }
        match o.target {
            Some(Target { macs: Some(f), latency: None }) | Some(Target { macs: None, latency: Some(f) }) if !(f > 0.0 && f <= 1.0) => bail!("prune target {f} must be a fraction in (0, 1] of the unpruned model"),
            Some(Target { macs: Some(_), latency: Some(_) }) | Some(Target { macs: None, latency: None }) => bail!("prune target: give exactly one of macs or latency (a fraction of the unpruned model), e.g. target: {{macs: 0.3}}"),
            _ => Ok(()),
        }
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let o = &self.options;
        let mut clock = Clock::default();
        // What a target counts from: the model with all its levels (the pruned model's input
        // when none can go).
        let with_levels = o.unused_levels.is_some().then(|| model.clone());
        let levels = match o.unused_levels {
            Some(share) => Some(drop_unused_levels(model, cx, share, o.seed)?),
            None => None,
        };
        clock.lap("levels");
        let original = model.clone();
        let whole = with_levels.as_ref().unwrap_or(&original);
        let g = original.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        let analysis = analyse(&graph, &inf, &o.ignore);

        // Frames are needed for activation importance and compensation; otherwise they only
        // measure the result, and a model they cannot feed is measured without them.
        let needs_frames = o.importance == Criterion::Activation || o.compensate != Mode::None;
        let (feeds, source) = match image_feeds(&graph, &inf, cx.calib.as_deref(), o.calib_frames, o.seed) {
            Ok(f) => f,
            Err(e) if needs_frames => return Err(e),
            Err(e) => (Vec::new(), format!("none ({e})")),
        };

        let (scores, fallback) = match o.importance {
            Criterion::L1 => (importance::magnitude(&graph, &analysis, false), 0),
            Criterion::L2 => (importance::magnitude(&graph, &analysis, true), 0),
            Criterion::BnGamma => importance::bn_gamma(&graph, &analysis),
            Criterion::Activation => (importance::activation(&analysis, &mean_abs(&original, &analysis, &feeds)?), 0),
        };
        clock.lap("frames_and_importance");
        let opset = crate::onnx::edit::default_opset(model).unwrap_or(13);
        // `check` refused a target together with ratios.
        let (per_group, sensitivity) = match (o.target, &o.ratios) {
            (_, Some(r)) => (Some(r.iter().map(|(k, v)| (k.clone(), *v)).collect()), None),
            (None, None) => (None, None),
            (Some(target), None) => {
                let feeds = feeds.get(..o.sensitivity_frames.min(feeds.len())).filter(|f| !f.is_empty()).ok_or_else(|| anyhow!("a pruning target needs calibration frames: {source}"))?;
                let (ratios, report) = allocate(whole, &original, &analysis, &scores, o, opset, target, feeds)?;
                if report["met"] == false {
                    cx.warn(format!("the target {target:?} is out of reach with ratios up to {}; pruned as far as the levels go", LEVELS[LEVELS.len() - 1]));
                }
                (Some(ratios), Some(report))
            }
        };
        clock.lap("sensitivity");
        let plan = select(&analysis, &scores, &SelectOptions { ratio: o.ratio, round_to: o.round_to, scope: o.scope, per_group });
        let kept = apply::kept_positions(&analysis, &plan.keep)?;
        let pg = super::graph_mut(model)?;
        let rewritten = apply::apply(pg, &analysis, &kept, opset)?;
        crate::ir::rewrite::dce::eliminate(pg)?;
        check_outputs(&original, model)?;
        // A scene specialization before pruning already left the full model as the teacher:
        // recovery then distills from it, through both cuts.
        cx.record_cut(|| original.clone(), &kept);
        clock.lap("rewrite");

        let (fit, held_out): (Vec<_>, Vec<_>) = feeds.iter().enumerate().partition(|(i, _)| feeds.len() < 4 || i % 4 != 3);
        // Compensation runs both models once per depth and frame: at 640x480 a few frames
        // already give hundreds of thousands of pixel samples.
        let pixels = feeds.first().map_or(1, |f| f[0].1.len()).max(1);
        let fit: Vec<Vec<(String, Tensor)>> = fit.into_iter().map(|(_, f)| f.clone()).take(COMPENSATION_PIXELS.div_ceil(pixels).max(2)).collect();
        let held_out: Vec<Vec<(String, Tensor)>> = if held_out.is_empty() { fit.clone() } else { held_out.into_iter().map(|(_, f)| f.clone()).collect() };
        let uncompensated = (o.compensate != Mode::None).then(|| model.clone());
        let comp = compensate::compensate(&original, model, &kept, &fit, &compensate::Options { mode: o.compensate, lambda: o.ridge, max_positions: MAX_REGRESSION_POSITIONS })?;
        crate::ir::rewrite::dce::eliminate(super::graph_mut(model)?)?;
        clock.lap("compensation");

        let mut errors = serde_json::Map::new();
        let mut compensation_kept = o.compensate != Mode::None;
        if !held_out.is_empty() {
            let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
            let reference = ReferenceOutputs::new(&original, &held_out, threads, None)?;
            let result = reference.errors(model)?;
            if let Some(u) = uncompensated {
                let before = reference.errors(&u)?;
                // Compensation stays only where it helps on frames it never saw: the worst
                // output group (boxes, objectness, classes judged apart) must improve.
                compensation_kept = worst_rel_l2(&result) < worst_rel_l2(&before);
                if !compensation_kept {
                    *model = u;
                }
                errors.insert("uncompensated".into(), by_name(&before));
                errors.insert("compensated".into(), by_name(&result));
            } else {
                errors.insert("pruned".into(), by_name(&result));
            }
        }
        clock.lap("held_out_check");
        let (before, after) = (counts(whole)?, counts(model)?);
        let pruned_groups = plan.groups.iter().filter(|p| p.after < p.before).count();
        Ok(serde_json::json!({
            "ratio": if o.target.is_some() { serde_json::Value::Null } else { o.ratio.into() },
            "target": o.target,
            "sensitivity": sensitivity,
            "unused_levels": levels,
            "importance": o.importance,
            "importance_fallback_classes": fallback,
            "scope": o.scope,
            "round_to": o.round_to,
            "groups_pruned": pruned_groups,
            "groups_kept": plan.groups.len() - pruned_groups,
            "channels_before": plan.groups.iter().map(|p| p.before).sum::<usize>(),
            "channels_after": plan.groups.iter().map(|p| p.after).sum::<usize>(),
            "macs_ratio": after.macs as f64 / before.macs.max(1) as f64,
            "params_ratio": after.params as f64 / before.params.max(1) as f64,
            "tensors_rewritten": rewritten,
            "compensation": { "mode": o.compensate, "kept": compensation_kept, "frames_fit": fit.len(), "work": comp },
            "calibration": source,
            "held_out_frames": if errors.is_empty() { 0 } else { held_out.len() },
            "output_rel_l2": errors,
            "seconds": clock.laps,
            "groups": plan.groups,
        }))
    }
}

/// Removes the detection levels holding at most `max_share` of the model's detections on
/// calibration frames; says each level's share. A model without a decode the measurement
/// reads keeps every level, with a warning.
fn drop_unused_levels(model: &mut ModelProto, cx: &mut PassContext, max_share: f64, seed: u64) -> Result<serde_json::Value> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let head = {
        let graph = Graph::build(g)?;
        let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
        crate::analysis::head::detect(&graph, &infer(&graph), &outputs)
    };
    if head.kind == crate::analysis::head::HeadKind::Raw || head.output.is_none() {
        cx.warn("unused_levels: the model has no YOLOv5 or YOLOv8 decode to count detections by; every level kept");
        return Ok(serde_json::json!({ "skipped": "no decoded detection output" }));
    }
    let (_, _, levels) = crate::scene::geometry::levels(g)?;
    let m = Measure { calib: cx.calib.as_deref(), frames: LEVEL_FRAMES, seed, size: [0.0, f32::INFINITY], score: LEVEL_SCORE };
    let (shares, source) = detection_shares(model, &head, &levels, &m)?;
    // No detection at all says nothing about the levels: all shares are 0 then.
    let keep: Vec<bool> = if shares.iter().all(|&s| s == 0.0) { vec![true; levels.len()] } else { shares.iter().map(|&s| s > max_share).collect() };
    if !keep.iter().any(|&k| k) {
        bail!("prune unused_levels {max_share} leaves no detection level: each holds at most that share of the detections ({shares:.3?}); give a smaller share");
    }
    if keep.iter().any(|&k| !k) {
        drop_levels(model, &keep, None)?;
    }
    Ok(serde_json::json!({
        "max_share": max_share,
        "measured_on": source,
        "levels": levels.iter().zip(&shares).zip(&keep).map(|((l, s), k)| serde_json::json!({ "stride": l.stride, "share": s, "kept": k })).collect::<Vec<_>>(),
    }))
}

/// Sensitivity of every prunable group at each level, then the per-group ratios meeting
/// `target` with the least predicted damage (see `prune::sensitivity`). The target counts
/// from `whole`, the model before its unused levels went (`original` otherwise).
#[allow(clippy::too_many_arguments)]
fn allocate(whole: &ModelProto, original: &ModelProto, analysis: &crate::analysis::channels::ChannelAnalysis, scores: &[f64], o: &Options, opset: i64, target: Target, feeds: &[Vec<(String, Tensor)>]) -> Result<(HashMap<String, f64>, serde_json::Value)> {
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let pruned = |ratios: &HashMap<String, f64>| -> Result<(ModelProto, crate::prune::Plan)> {
        let plan = select(analysis, scores, &SelectOptions { ratio: 0.0, round_to: o.round_to, scope: o.scope, per_group: Some(ratios.clone()) });
        let kept = apply::kept_positions(analysis, &plan.keep)?;
        let mut m = original.clone();
        let g = super::graph_mut(&mut m)?;
        apply::apply(g, analysis, &kept, opset)?;
        crate::ir::rewrite::dce::eliminate(g)?;
        Ok((m, plan))
    };
    let base = counts(original)?.macs;
    let mut groups = Vec::new();
    let prunable = analysis.groups.iter().filter(|g| g.frozen.is_none()).count();
    // Minutes on a larger model: say how far it is (hidden when stderr is not a terminal).
    let pb = indicatif::ProgressBar::new(prunable as u64);
    pb.set_style(indicatif::ProgressStyle::with_template("prune: sensitivity of each group [{bar:30}] {pos}/{len} ({elapsed})").expect("valid template").progress_chars("=> "));
    let reference = ReferenceOutputs::new(original, feeds, threads, None)?;
    for (gi, g) in analysis.groups.iter().enumerate().filter(|(_, g)| g.frozen.is_none()) {
        pb.inc(1);
        let mut levels: Vec<Level> = Vec::new();
        let cap = max_ratio(&o.max_ratios, &g.anchor);
        for &ratio in LEVELS.iter().filter(|&&r| r <= cap) {
            let (m, plan) = pruned(&HashMap::from([(g.anchor.clone(), ratio)]))?;
            let keep = plan.groups[gi].after;
            if keep >= g.classes.len() || levels.last().is_some_and(|l| l.keep == keep) {
                continue;
            }
            let damage = reference.damage(&m)?;
            levels.push(Level { ratio, keep, damage, macs_saved: base.saturating_sub(counts(&m)?.macs) });
        }
        if !levels.is_empty() {
            groups.push(GroupSensitivity { anchor: g.anchor.clone(), channels: g.classes.len(), levels, chosen: 0.0 });
        }
    }
    pb.finish_and_clear();
    let mut macs_of = |r: &HashMap<String, f64>| -> Result<u64> { Ok(counts(&pruned(r)?.0)?.macs) };
    let (ratios, met) = match (target.macs, target.latency) {
        (Some(f), None) => allocate_ratios(&mut groups, Budget::Macs((f * counts(whole)?.macs as f64) as u64), &mut macs_of)?,
        (None, Some(f)) => {
            let mut reference = OrtRuntime::new(whole)?;
            let mut check = |r: &HashMap<String, f64>| -> Result<bool> { Ok(latency_ratio(&mut reference, &pruned(r)?.0, &feeds[0])? <= f) };
            allocate_ratios(&mut groups, Budget::Check(&mut check), &mut macs_of)?
        }
        _ => bail!("prune target: give exactly one of macs or latency (a fraction of the unpruned model), e.g. target: {{macs: 0.3}}"),
    };
    Ok((ratios, serde_json::json!({ "met": met, "levels": LEVELS, "frames": feeds.len(), "groups": groups })))
}

/// The largest ratio `max_ratios` lets a target give the group anchored at `anchor`.
fn max_ratio(max_ratios: &std::collections::BTreeMap<String, f64>, anchor: &str) -> f64 {
    max_ratios.iter().filter(|(p, _)| anchor.starts_with(p.as_str())).max_by_key(|(p, _)| p.len()).map_or(1.0, |(_, &r)| r)
}

/// ONNX Runtime latency of `candidate` over `reference`'s, timed interleaved on one frame.
fn latency_ratio(reference: &mut OrtRuntime, candidate: &ModelProto, feed: &[(String, Tensor)]) -> Result<f64> {
    let mut c = OrtRuntime::new(candidate)?;
    let t = crate::runtime::latency::interleaved(&mut [("reference".into(), reference as &mut dyn Runtime, feed.to_vec()), ("candidate".into(), &mut c, feed.to_vec())], 7)?;
    Ok(t[1].median_ms / t[0].median_ms.max(1e-9))
}

/// Mean |activation| per channel of every analysed value read by a convolution.
fn mean_abs(model: &ModelProto, a: &crate::analysis::channels::ChannelAnalysis, feeds: &[Vec<(String, Tensor)>]) -> Result<HashMap<String, Vec<f64>>> {
    let g = model.graph.as_ref().expect("checked");
    let names: Vec<String> = g.node.iter().filter(|n| n.op_type == "Conv").map(|n| n.input[0].clone()).filter(|v| a.values.contains_key(v)).collect::<std::collections::BTreeSet<_>>().into_iter().collect();
    let mut rt = OrtRuntime::new(&expose_outputs(model, &names))?;
    let mut sums: HashMap<String, Vec<f64>> = HashMap::new();
    for f in feeds {
        for (n, t) in rt.run(f)? {
            let (Some(s), Some(v)) = (a.values.get(&n), t.as_f32()) else { continue };
            let plane = v.len() / s.channels.max(1);
            let acc = sums.entry(n).or_insert_with(|| vec![0.0; s.channels]);
            for (c, chunk) in v.chunks(plane.max(1)).enumerate() {
                acc[c % s.channels] += chunk.iter().map(|x| x.abs() as f64).sum::<f64>() / plane as f64;
            }
        }
    }
    Ok(sums)
}

/// Outputs must keep their names and shapes: the deployment's post-processing depends on them.
fn check_outputs(original: &ModelProto, pruned: &ModelProto) -> Result<()> {
    let shapes = |m: &ModelProto| -> Result<Vec<(String, Option<Vec<usize>>)>> {
        let g = m.graph.as_ref().expect("checked");
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        Ok(g.output.iter().map(|o| (o.name.clone(), inf.shape(&o.name))).collect())
    };
    let (a, b) = (shapes(original)?, shapes(pruned)?);
    if a != b {
        bail!("pruning changed the outputs ({a:?} -> {b:?}); this is a bug in the channel analysis, please report it");
    }
    Ok(())
}

/// Rel L2 per output, and per channel group of a detection output as `output/group`.
pub(crate) fn by_name(errors: &[OutputError]) -> serde_json::Value {
    errors.iter().map(|e| (e.group.map_or(e.output.clone(), |g| format!("{}/{g}", e.output)), serde_json::json!(e.error.rel_l2))).collect::<serde_json::Map<_, _>>().into()
}
