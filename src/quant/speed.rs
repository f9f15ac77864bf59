//! Speed-aware precision: a quantized convolution stays INT8 only where ONNX Runtime runs the
//! model faster that way on the machine that compiles.
//!
//! Integer kernels are not faster everywhere. ORT's QLinearConv lowers a convolution to a GEMM
//! over its input channels times kernel taps; with one input channel (the frame) that is 9
//! terms per output, too few to fill its u8 kernels, while its float NCHWc convolution has a
//! direct path for it. Measured on the full-size v5 pruned for speed (640x480, 2 cores): the
//! first convolution (1 -> 8 channels, 3x3) took 4.5 ms as QLinearConv and 0.5 ms as float,
//! yet the whole model got only 2% faster with it float: the frame's quantization and ORT's
//! NHWC transpose move to the convolution's 8-channel output.
//!
//! So kernel times only pick the candidates: the quantized convolutions with the largest share
//! of the INT8 model's profiled kernel time. Each is tried float in turn, and stays float only
//! if the whole model, timed interleaved with the current choice, got faster by [`MIN_GAIN`]
//! (median and fastest run). A float layer never costs accuracy, so a choice that noise let
//! through costs at most speed.

use super::plan::{plan, Plan};
use super::qdq::Emitted;
use crate::ir::Graph;
use crate::onnx::proto::ModelProto;
use crate::runtime::ort_profile::profile;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use crate::runtime::latency::interleaved;
use anyhow::Result;
use ort::session::builder::GraphOptimizationLevel;
use std::collections::HashSet;

/// A convolution is a candidate when its integer kernel takes at least this share of the
/// model's profiled kernel time: below it, no gain could clear [`MIN_GAIN`].
const MIN_SHARE: f64 = 0.03;
/// Candidates tried, largest share first (each costs two sessions and [`TIMED_RUNS`] pairs).
const MAX_TRIED: usize = 4;
/// The whole model must get this much faster (median and fastest of interleaved runs) for a
/// layer to go float: medians of one model's interleaved runs differ by 1-2% here, so a
/// smaller gain is noise.
const MIN_GAIN: f64 = 0.03;
const TIMED_RUNS: usize = 15;
/// What the plan says of a layer this search keeps float.
pub const REASON: &str = "faster in float on this machine (ONNX Runtime, measured)";

pub struct Search<'a> {
    pub graph: &'a Graph<'a>,
    /// Nodes float already (keep_float, mixed precision).
    pub keep: &'a HashSet<String>,
    /// One input feed to time on.
    pub feed: &'a [(String, Tensor)],
    pub threads: usize,
}

#[derive(Default)]
pub struct Outcome {
    /// The plan and model with the faster float layers (None: none was faster).
    pub chosen: Option<(Plan, (ModelProto, Emitted))>,
    pub report: serde_json::Value,
}

/// Tries the heaviest quantized convolutions of `current` (planned by `current_plan`) in float.
pub fn float_where_faster(s: &Search, current_plan: &Plan, current: &ModelProto, emit_with: &dyn Fn(&Plan) -> Result<(ModelProto, Emitted)>) -> Result<Outcome> {
    let prof = profile(current, s.feed, s.threads)?;
    let total: f64 = prof.kernels.iter().map(|k| k.ms).sum();
    let convs: HashSet<&str> = current_plan.quantized.iter().map(|&i| s.graph.node(i)).filter(|n| n.op_type == "Conv").map(|n| n.name.as_str()).collect();
    let mut candidates: Vec<_> = prof.kernels.iter().filter(|k| k.op == "QLinearConv" && convs.contains(k.source()) && k.ms >= MIN_SHARE * total).collect();
    candidates.sort_by(|a, b| b.ms.total_cmp(&a.ms));
    candidates.truncate(MAX_TRIED);

    let mut names = s.keep.clone();
    let mut faster: HashSet<String> = HashSet::new();
    let mut best = OrtRuntime::with_options(current, GraphOptimizationLevel::Level3, s.threads)?;
    let mut out = Outcome::default();
    let mut tried = Vec::new();
    for k in candidates {
        let (mut with, mut with_faster) = (names.clone(), faster.clone());
        with.insert(k.source().to_string());
        with_faster.insert(k.source().to_string());
        let p = plan_with_reason(s.graph, &with, &with_faster);
        let candidate = emit_with(&p)?;
        let mut rt = OrtRuntime::with_options(&candidate.0, GraphOptimizationLevel::Level3, s.threads)?;
        let t = interleaved(&mut [("int8".into(), &mut best as &mut dyn Runtime, s.feed.to_vec()), ("float".into(), &mut rt as &mut dyn Runtime, s.feed.to_vec())], TIMED_RUNS)?;
        // Both the median and the fastest run must show the gain: a burst of load on the
        // machine moves one of them, rarely both.
        let kept = t[1].median_ms < t[0].median_ms * (1.0 - MIN_GAIN) && t[1].min_ms < t[0].min_ms * (1.0 - MIN_GAIN);
        tried.push(serde_json::json!({"node": k.source(), "int8_kernel_ms": k.ms, "model_ms_int8": t[0].median_ms, "model_ms_float": t[1].median_ms, "min_ms_int8": t[0].min_ms, "min_ms_float": t[1].min_ms, "kept_float": kept}));
        if kept {
            (names, faster) = (with, with_faster);
            best = rt;
            out.chosen = Some((p, candidate));
        }
    }
    out.report = serde_json::json!({
        "profiled_run_ms": prof.run_ms,
        "profiled_kernel_ms": total,
        "min_share": MIN_SHARE,
        "min_gain": MIN_GAIN,
        "timed_runs": TIMED_RUNS,
        "tried": tried,
    });
    Ok(out)
}

/// The plan with `with` float, where the nodes in `faster` say this search chose them.
fn plan_with_reason(g: &Graph, with: &HashSet<String>, faster: &HashSet<String>) -> Plan {
    let mut p = plan(g, with);
    for (&i, why) in p.float.iter_mut() {
        if faster.contains(&g.node(i).name) {
            *why = REASON.to_string();
        }
    }
    p
}
