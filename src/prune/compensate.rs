//! Training-free compensation: after channels go, refit the convolutions that read them so
//! their outputs match the unpruned model's on calibration frames.
//!
//! Layers are corrected in order of depth. At each depth the pruned model, with every
//! shallower layer already corrected, is run on the calibration frames next to the
//! original: a convolution sees X' (its pruned, drifted input) where the original saw X
//! and produced Y. Same-depth layers never feed each other, so one run per depth suffices.
//!
//! `lstsq` refits the kept output rows by ridge regression, pulled towards the pruned
//! weights: over the unrolled k×k×C' receptive field of X' to Y when that is at most
//! [`MAX_UNROLLED`] features (exact least squares on the layer's output, intercept as the
//! bias), otherwise per pixel from X' to X (W' = W·M per tap, for each layer's wide 3x3
//! convolutions at full width). The ridge strength (1x to 1000x the configured one, or no
//! refit at all) is chosen per regression on held-out check frames. Samples are positions
//! drawn at random from strata, never a regular stride. `bias` (and `lstsq` after an
//! input-space refit) sets the bias so the output's per-channel mean equals the original's:
//! b' = b + Σ W·E[X at tap] − Σ W'·E[X' at tap], with tap means over the zero-padded
//! input taken exactly (borders matter at 8x6 strides).

use crate::ridge::{spread_positions, Moments};
use crate::ir::{infer, Graph};
use crate::onnx::attr;
use crate::onnx::edit::{expose_outputs, initializer, set_input_constant};
use crate::onnx::proto::{GraphProto, ModelProto, NodeProto};
use crate::onnx::tensor_proto::to_tensor;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    None,
    /// Mean-shift correction of the biases only.
    Bias,
    /// Ridge refit of dense convolutions, then mean-shift correction.
    Lstsq,
}

pub struct Options {
    pub mode: Mode,
    /// Ridge strength relative to the mean feature variance.
    pub lambda: f64,
    /// At most this many pixel positions per frame enter a regression (an even subsample).
    pub max_positions: usize,
}

/// Largest unrolled receptive field (C'·k·k) fitted on the output directly: its Gram matrix
/// costs samples × features² per layer (a 3x3 conv keeping 32 input channels is 288).
pub const MAX_UNROLLED: usize = 320;
/// Floats of the original's values kept in memory at once (1 GiB): at 640x480 a batch then
/// spans a few depths; a fixture's whole network fits in one.
const ORIGINAL_VALUES_BUDGET: usize = 1 << 28;
/// Samples per unrolled feature in an output fit, over all frames.
const SAMPLES_PER_FEATURE: usize = 32;

#[derive(Serialize, Default)]
pub struct Report {
    /// Refit on the layer's output (unrolled receptive field).
    pub refit_output: usize,
    /// Refit in input space (per pixel, per tap).
    pub refit_input: usize,
    /// Depths processed: one run of both models per frame each.
    pub depths: usize,
    pub bias_corrected: usize,
    /// Convolutions whose regression was ill-posed: only their bias was corrected.
    pub not_refit: Vec<String>,
    /// Per regression, what the held-out frame chose: a ridge strength (× the configured
    /// one), or `pruned weights` when no refit beat them there.
    pub choices: std::collections::BTreeMap<String, usize>,
    /// Seconds per phase: the original's runs, sessions of the pruned model, its runs,
    /// accumulating statistics, solving.
    pub seconds: std::collections::BTreeMap<&'static str, f64>,
}

/// Convolution geometry along one spatial axis.
#[derive(Clone, Copy)]
struct Axis {
    k: usize,
    stride: usize,
    dilation: usize,
    pad: usize,
    input: usize,
    output: usize,
}

impl Axis {
    /// Input index read by output `o` at tap `t`, if inside the (unpadded) input.
    fn source(&self, o: usize, t: usize) -> Option<usize> {
        let p = (o * self.stride + t * self.dilation) as isize - self.pad as isize;
        (p >= 0 && (p as usize) < self.input).then_some(p as usize)
    }
}

fn geometry(n: &NodeProto, w: &Tensor, x: &[usize], y: &[usize]) -> Option<[Axis; 2]> {
    let k = attr::ints(n, "kernel_shape").map(|v| v.iter().map(|&d| d as usize).collect()).unwrap_or_else(|| w.shape[2..].to_vec());
    let s = attr::ints(n, "strides").unwrap_or(vec![1, 1]);
    let d = attr::ints(n, "dilations").unwrap_or(vec![1, 1]);
    let pads = attr::ints(n, "pads").unwrap_or(vec![0; 4]);
    if k.len() != 2 || s.len() != 2 || d.len() != 2 || pads.len() != 4 {
        return None;
    }
    let auto = attr::string(n, "auto_pad", "NOTSET");
    let axis = |i: usize| {
        let span = (k[i] - 1) * d[i] as usize + 1;
        let pad = match auto.as_str() {
            "SAME_UPPER" | "SAME_LOWER" => {
                let total = ((y[2 + i] - 1) * s[i] as usize + span).saturating_sub(x[2 + i]);
                if auto == "SAME_UPPER" { total / 2 } else { total - total / 2 }
            }
            "VALID" => 0,
            _ => pads[i].max(0) as usize,
        };
        Axis { k: k[i], stride: s[i].max(1) as usize, dilation: d[i].max(1) as usize, pad, input: x[2 + i], output: y[2 + i] }
    };
    Some([axis(0), axis(1)])
}

/// Σ over output positions of the input under each tap, per channel: [C][kh*kw], for a
/// [N, C, H, W] input. Separable: row sums per column tap, then over the row taps.
fn tap_sums(x: &[f32], c: usize, geo: &[Axis; 2]) -> Vec<f64> {
    let [gy, gx] = *geo;
    let plane = gy.input * gx.input;
    let n = x.len() / (c * plane).max(1);
    let mut out = vec![0.0; c * gy.k * gx.k];
    let cols: Vec<Vec<usize>> = (0..gx.k).map(|t| (0..gx.output).filter_map(|o| gx.source(o, t)).collect()).collect();
    let rows: Vec<Vec<usize>> = (0..gy.k).map(|t| (0..gy.output).filter_map(|o| gy.source(o, t)).collect()).collect();
    for b in 0..n {
        for ch in 0..c {
            let p = &x[(b * c + ch) * plane..(b * c + ch + 1) * plane];
            for (tx, cs) in cols.iter().enumerate() {
                let r: Vec<f64> = (0..gy.input).map(|yy| cs.iter().map(|&xx| p[yy * gx.input + xx] as f64).sum()).collect();
                for (ty, rs) in rows.iter().enumerate() {
                    out[(ch * gy.k + ty) * gx.k + tx] += rs.iter().map(|&yy| r[yy]).sum::<f64>();
                }
            }
        }
    }
    out
}

/// Per output row: Σ_c Σ_t W[r, c, t] · T[segment(r) * cpg + c, t].
fn mean_response(w: &[f32], rows: usize, cpg: usize, taps: usize, segment: impl Fn(usize) -> usize, t: &[f64]) -> Vec<f64> {
    (0..rows)
        .map(|r| {
            let base = segment(r) * cpg;
            (0..cpg).map(|c| (0..taps).map(|k| w[(r * cpg + c) * taps + k] as f64 * t[(base + c) * taps + k]).sum::<f64>()).sum()
        })
        .collect()
}

/// One convolution to correct at a depth: its pruned and original forms.
struct Job {
    node: usize,
    x: String,
    y: String,
    orig: NodeProto,
    w_orig: Tensor,
    w_new: Tensor,
    geo: [Axis; 2],
    /// Kept input positions (all when its input lost none).
    xk: Vec<usize>,
    /// Kept output positions.
    ys: Vec<usize>,
    group_o: usize,
    group_p: usize,
}

impl Job {
    fn taps(&self) -> usize {
        self.geo[0].k * self.geo[1].k
    }
    /// Unrolled features per output row of the pruned layer.
    fn unrolled(&self) -> usize {
        self.w_new.shape[1] * self.taps()
    }
    fn output_fit(&self) -> bool {
        self.unrolled() <= MAX_UNROLLED
    }
}

/// Depth of every value: the number of convolutions on the longest path from an input.
fn depths(g: &Graph) -> HashMap<String, usize> {
    let mut d: HashMap<String, usize> = HashMap::new();
    for &i in &g.order {
        let n = g.node(i);
        let base = n.input.iter().filter_map(|v| d.get(v)).copied().max().unwrap_or(0);
        let out = base + usize::from(matches!(n.op_type.as_str(), "Conv" | "ConvTranspose"));
        for o in &n.output {
            d.insert(o.clone(), out);
        }
    }
    d
}

/// Values that differ from the original because channels in `kept` were pruned.
fn drifted(g: &Graph, kept: &HashMap<String, Vec<usize>>) -> std::collections::HashSet<String> {
    let mut out: std::collections::HashSet<String> = kept.keys().cloned().collect();
    for &i in &g.order {
        let n = g.node(i);
        if n.input.iter().any(|v| out.contains(v)) {
            out.extend(n.output.iter().cloned());
        }
    }
    out
}

/// Compensates `pruned` (the pruning of `original` with `kept` channel positions) on `feeds`.
pub fn compensate(original: &ModelProto, pruned: &mut ModelProto, kept: &HashMap<String, Vec<usize>>, feeds: &[Vec<(String, Tensor)>], opts: &Options) -> Result<Report> {
    let mut report = Report::default();
    if opts.mode == Mode::None || feeds.is_empty() {
        return Ok(report);
    }
    let orig_g = original.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let orig_graph = Graph::build(orig_g)?;
    let inf = infer(&orig_graph);
    let mut jobs: Vec<(usize, Job)> = Vec::new();
    {
        let g = pruned.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let graph = Graph::build(g)?;
        let depth = depths(&graph);
        let drift = drifted(&graph, kept);
        let decode = crate::analysis::channels::decode_nodes(&graph);
        for (i, n) in g.node.iter().enumerate() {
            if n.op_type != "Conv" || !n.domain.is_empty() || !drift.contains(&n.input[0]) || decode.contains(&i) {
                continue;
            }
            let Some(o) = orig_g.node.iter().find(|m| m.output.first() == n.output.first()) else { continue };
            let weight = |gp: &crate::onnx::proto::GraphProto, name: &str| initializer(gp, name).and_then(|t| to_tensor(t).ok()).filter(|t| t.as_f32().is_some());
            let (Some(w_orig), Some(w_new)) = (weight(orig_g, &o.input[1]), weight(g, &n.input[1])) else { continue };
            let (Some(xs), Some(yshape)) = (inf.shape(&o.input[0]), inf.shape(&o.output[0])) else { continue };
            let Some(geo) = geometry(o, &w_orig, &xs, &yshape) else { continue };
            let job = Job {
                node: i,
                x: o.input[0].clone(),
                y: o.output[0].clone(),
                xk: kept.get(&o.input[0]).cloned().unwrap_or_else(|| (0..xs[1]).collect()),
                ys: kept.get(&o.output[0]).cloned().unwrap_or_else(|| (0..w_orig.shape[0]).collect()),
                group_o: attr::int(o, "group", 1).max(1) as usize,
                group_p: attr::int(n, "group", 1).max(1) as usize,
                orig: o.clone(),
                w_orig,
                w_new,
                geo,
            };
            jobs.push((depth.get(&n.input[0]).copied().unwrap_or(0), job));
        }
    }
    jobs.sort_by_key(|(d, j)| (*d, j.node));
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    // Basic optimizations: a session per depth is built, and building is what costs here.
    let level = ort::session::builder::GraphOptimizationLevel::Level1;
    let mut stages: Vec<Vec<&Job>> = Vec::new();
    for (i, (d, j)) in jobs.iter().enumerate() {
        if i == 0 || jobs[i - 1].0 != *d {
            stages.push(Vec::new());
        }
        stages.last_mut().expect("pushed").push(j);
    }
    let original_values = |stage: &[&Job]| -> Vec<String> {
        let mut v: Vec<String> = stage.iter().map(|j| j.x.clone()).collect();
        v.extend(stage.iter().filter(|j| opts.mode == Mode::Lstsq && j.output_fit()).map(|j| j.y.clone()));
        v
    };
    let floats = |values: &[String]| -> usize { values.iter().map(|v| inf.shape(v).map_or(0, |s| s.iter().product())).sum::<usize>() * feeds.len() };
    let mut clock = crate::clock::Clock::default();
    let mut at = 0;
    while at < stages.len() {
        // The original does not change: one run per frame serves every depth of a batch, as
        // many depths as fit in ORIGINAL_VALUES_BUDGET (each depth's run of the pruned model
        // still follows the corrections of the depths before it).
        let mut batch_values: Vec<String> = original_values(&stages[at]);
        let mut end = at + 1;
        while end < stages.len() {
            let mut more = batch_values.clone();
            more.extend(original_values(&stages[end]));
            if floats(&more) > ORIGINAL_VALUES_BUDGET {
                break;
            }
            batch_values = more;
            end += 1;
        }
        batch_values.sort();
        batch_values.dedup();
        let mut orig_rt = OrtRuntime::with_options(&truncated(original, &batch_values)?, level, threads)?;
        let mut kept_values: Vec<HashMap<String, Vec<f32>>> = Vec::with_capacity(feeds.len());
        for f in feeds {
            kept_values.push(orig_rt.run(f)?.into_iter().map(|(n, t)| t.as_f32().map(|v| (n, v.to_vec())).ok_or_else(|| anyhow!("value is not float32"))).collect::<Result<_>>()?);
        }
        drop(orig_rt);
        clock.lap("original_runs");
        for stage in &stages[at..end] {
            report.depths += 1;
            let xs: Vec<String> = stage.iter().map(|j| j.x.clone()).collect::<std::collections::BTreeSet<_>>().into_iter().collect();
            let mut pruned_rt = OrtRuntime::with_options(&truncated(pruned, &xs)?, level, threads)?;
            let mut acc: Vec<Accumulator> = stage.iter().map(|j| Accumulator::new(j, opts.mode, feeds.len())).collect();
            clock.lap("sessions");
            for (f, ro) in feeds.iter().zip(&kept_values) {
                let rp = pruned_rt.run(f)?;
                clock.lap("pruned_runs");
                let orig = |v: &str| ro.get(v).ok_or_else(|| anyhow!("value {v} was not returned"));
                for (j, a) in stage.iter().zip(acc.iter_mut()) {
                    let xp = rp.iter().find(|(n, _)| *n == j.x).and_then(|(_, t)| t.as_f32()).ok_or_else(|| anyhow!("value {} was not returned as float32", j.x))?;
                    let y = if a.output.is_empty() { None } else { Some(orig(&j.y)?.as_slice()) };
                    let samples = (SAMPLES_PER_FEATURE * j.unrolled()).div_ceil(feeds.len()).min(opts.max_positions);
                    a.add(j, orig(&j.x)?, xp, y, opts.max_positions, samples);
                }
                clock.lap("statistics");
            }
            let g = pruned.graph.as_mut().expect("checked");
            for (j, a) in stage.iter().zip(acc) {
                let name = g.node[j.node].name.clone();
                match a.finish(j, feeds.len(), opts.lambda, orig_g, &mut report.choices)? {
                    Some((w, b, how)) => {
                        match how {
                            Fit::Output => report.refit_output += 1,
                            Fit::Input => report.refit_input += 1,
                            Fit::Bias => {}
                        }
                        set_input_constant(g, j.node, 1, &w, "compensated");
                        set_input_constant(g, j.node, 2, &b, "compensated");
                        report.bias_corrected += 1;
                    }
                    None => report.not_refit.push(name),
                }
            }
            clock.lap("solve");
        }
        at = end;
    }
    report.seconds = clock.laps;
    Ok(report)
}

/// `model` computing only `values`: everything past them is cut, so a shallow depth's
/// runs cost a shallow model.
fn truncated(model: &ModelProto, values: &[String]) -> Result<ModelProto> {
    let mut m = expose_outputs(model, values);
    let g = m.graph.as_mut().expect("checked");
    g.output.retain(|o| values.contains(&o.name));
    crate::ir::rewrite::dce::eliminate(g)?;
    Ok(m)
}

enum Fit {
    Output,
    Input,
    Bias,
}

/// Statistics of one convolution over the frames.
struct Accumulator {
    /// Tap means of X (original) and X' (pruned), summed over frames: [C][taps].
    taps_o: Vec<f64>,
    taps_p: Vec<f64>,
    /// Output fit: one regression per segment of the pruned layer (unrolled X' -> Y rows),
    /// on the fitting frames and on the check frames.
    output: Vec<Moments>,
    output_check: Vec<Moments>,
    /// Input fit: X' -> X per pixel (dense layers too wide to unroll), fitting and check.
    input: Option<(Moments, Moments)>,
    /// Frames added so far (each frame samples other positions), of `frames`.
    frames_seen: u64,
    frames: usize,
}

/// Ridge strengths tried, as multiples of the configured one; the check frames pick.
const RIDGE_MULTIPLIERS: [f64; 4] = [1.0, 10.0, 100.0, 1000.0];

/// Frame `k` of `frames` is held out to choose the ridge strength: every 4th, or the last
/// of 2 or 3. A refit must beat the pruned weights on frames it never saw: where pruning
/// left features with little relation to the original's (an untrained full-size network),
/// an unchecked refit fits noise and makes the output worse.
fn is_check_frame(k: u64, frames: usize) -> bool {
    frames >= 2 && (k % 4 == 3 || (frames < 4 && k as usize == frames - 1))
}

/// The refit `fit` (with `prior` as the ridge target) whose residual on `check` is least,
/// among the ridge strengths and `prior` itself, re-solved on all samples; with its label.
fn choose(fit: &Moments, check: &Moments, lambda: f64, prior: &[f64]) -> Option<(Vec<f64>, Vec<f64>, String)> {
    if check.n < 1.0 {
        let (mm, c) = fit.solve(lambda, Some(prior))?;
        return Some((mm, c, "1x".into()));
    }
    let mut best: Option<(f64, Option<f64>)> = None;
    for k in RIDGE_MULTIPLIERS.into_iter().map(Some).chain([None]) {
        let fitted = match k {
            Some(k) => fit.solve(lambda * k, Some(prior)),
            None => Some(fit.intercept_only(prior)),
        };
        if let Some((mm, c)) = fitted {
            let r = check.residual(&mm, &c);
            if r.is_finite() && best.is_none_or(|(b, _)| r < b) {
                best = Some((r, k));
            }
        }
    }
    let (_, k) = best?;
    let mut all = fit.clone();
    all.merge(check);
    match k {
        Some(k) => all.solve(lambda * k, Some(prior)).map(|(mm, c)| (mm, c, format!("{k}x"))),
        None => Some({
            let (mm, c) = all.intercept_only(prior);
            (mm, c, "pruned weights".into())
        }),
    }
}

impl Accumulator {
    fn new(j: &Job, mode: Mode, frames: usize) -> Accumulator {
        let (cin_o, cin_p) = (j.w_orig.shape[1] * j.group_o, j.xk.len());
        let rows = j.ys.len() / j.group_p.max(1);
        let lstsq = mode == Mode::Lstsq;
        Accumulator {
            taps_o: vec![0.0; cin_o * j.taps()],
            taps_p: vec![0.0; cin_p * j.taps()],
            output: if lstsq && j.output_fit() { (0..j.group_p).map(|_| Moments::new(j.unrolled(), rows)).collect() } else { Vec::new() },
            output_check: if lstsq && j.output_fit() { (0..j.group_p).map(|_| Moments::new(j.unrolled(), rows)).collect() } else { Vec::new() },
            input: (lstsq && !j.output_fit() && j.group_o == 1 && j.group_p == 1).then(|| (Moments::new(cin_p, cin_o), Moments::new(cin_p, cin_o))),
            frames_seen: 0,
            frames,
        }
    }

    /// `output_samples`: positions per frame for the unrolled fit (a multiple of its features
    /// over all frames is plenty with the ridge prior, and the Gram matrix is the cost).
    fn add(&mut self, j: &Job, x: &[f32], xp: &[f32], y: Option<&[f32]>, max_positions: usize, output_samples: usize) {
        let per = (j.geo[0].output * j.geo[1].output) as f64;
        let cin_o = self.taps_o.len() / j.taps();
        for (a, v) in self.taps_o.iter_mut().zip(tap_sums(x, cin_o, &j.geo)) {
            *a += v / per;
        }
        for (a, v) in self.taps_p.iter_mut().zip(tap_sums(xp, j.xk.len(), &j.geo)) {
            *a += v / per;
        }
        let [gy, gx] = j.geo;
        let plane = gy.input * gx.input;
        let check = is_check_frame(self.frames_seen, self.frames);
        if let Some((fit, held)) = self.input.as_mut() {
            let m = if check { held } else { fit };
            m.add_planes(xp, x, plane, &spread_positions(plane, max_positions, self.frames_seen));
        }
        if let Some(y) = y {
            let outs = gy.output * gx.output;
            let picks = spread_positions(outs, output_samples.max(1), self.frames_seen);
            let cpg = j.w_new.shape[1];
            let rows = j.ys.len() / j.group_p.max(1);
            let moments = if check { &mut self.output_check } else { &mut self.output };
            for (s, m) in moments.iter_mut().enumerate() {
                let mut cols: Vec<Vec<f64>> = Vec::with_capacity(cpg * j.taps());
                for c in 0..cpg {
                    let p = &xp[(s * cpg + c) * plane..(s * cpg + c + 1) * plane];
                    for ty in 0..gy.k {
                        for tx in 0..gx.k {
                            cols.push(picks.iter().map(|&o| match (gy.source(o / gx.output, ty), gx.source(o % gx.output, tx)) {
                                (Some(yy), Some(xx)) => p[yy * gx.input + xx] as f64,
                                _ => 0.0,
                            }).collect());
                        }
                    }
                }
                let targets: Vec<Vec<f64>> = (0..rows).map(|r| {
                    let row = j.ys[s * rows + r];
                    picks.iter().map(|&o| y[row * outs + o] as f64).collect()
                }).collect();
                m.add_columns(&cols, &targets);
            }
        }
        self.frames_seen += 1;
    }

    /// New (weight, bias) for the pruned layer, or None when its fit was ill-posed.
    fn finish(self, j: &Job, frames: usize, lambda: f64, orig_g: &GraphProto, choices: &mut std::collections::BTreeMap<String, usize>) -> Result<Option<(Tensor, Tensor, Fit)>> {
        let f = frames.max(1) as f64;
        let ntaps = j.taps();
        let mut weight = j.w_new.as_f32().expect("f32 checked").to_vec();
        let current_bias = |g: &GraphProto, n: &NodeProto| -> Result<Vec<f32>> {
            Ok(match n.input.get(2).filter(|s| !s.is_empty()) {
                Some(b) => to_tensor(initializer(g, b).ok_or_else(|| anyhow!("bias of {}", n.name))?)?.as_f32().map(<[f32]>::to_vec).ok_or_else(|| anyhow!("bias of {}", n.name))?,
                None => Vec::new(),
            })
        };
        let bias_o_all = current_bias(orig_g, &j.orig)?;
        let bias_o: Vec<f32> = if bias_o_all.is_empty() { vec![0.0; j.ys.len()] } else { j.ys.iter().map(|&r| bias_o_all[r]).collect() };
        if !self.output.is_empty() {
            let rows = j.ys.len() / j.group_p.max(1);
            let d = j.unrolled();
            let mut bias = vec![0.0f32; j.ys.len()];
            for (s, (m, held)) in self.output.iter().zip(&self.output_check).enumerate() {
                let prior: Vec<f64> = weight[s * rows * d..(s + 1) * rows * d].iter().map(|&v| v as f64).collect();
                let Some((mm, c, choice)) = choose(m, held, lambda, &prior) else { return Ok(None) };
                *choices.entry(choice).or_default() += 1;
                for (k, v) in mm.iter().enumerate() {
                    weight[s * rows * d + k] = *v as f32;
                }
                for r in 0..rows {
                    bias[s * rows + r] = c[r] as f32;
                }
            }
            return Ok(finite(j, weight, bias, Fit::Output));
        }
        let rows_o = j.w_orig.select(0, &j.ys).ok_or_else(|| anyhow!("weight rows of {}", j.orig.name))?;
        let wo = rows_o.as_f32().expect("f32 checked");
        let (cin_o, cin_p) = (j.w_orig.shape[1], j.w_new.shape[1]);
        let mut how = Fit::Bias;
        if let Some((m, held)) = &self.input {
            // Prior: the identity on the kept channels (X'[jj] stands for X[xk[jj]]).
            let mut prior = vec![0.0; cin_o * cin_p];
            for (jj, &c) in j.xk.iter().enumerate() {
                prior[c * cin_p + jj] = 1.0;
            }
            let Some((mm, _, choice)) = choose(m, held, lambda, &prior) else { return Ok(None) };
            *choices.entry(choice).or_default() += 1;
            for r in 0..j.ys.len() {
                for jj in 0..cin_p {
                    for t in 0..ntaps {
                        weight[(r * cin_p + jj) * ntaps + t] = (0..cin_o).map(|c| wo[(r * cin_o + c) * ntaps + t] as f64 * mm[c * cin_p + jj]).sum::<f64>() as f32;
                    }
                }
            }
            how = Fit::Input;
        }
        let to: Vec<f64> = self.taps_o.iter().map(|v| v / f).collect();
        let tp: Vec<f64> = self.taps_p.iter().map(|v| v / f).collect();
        let (per_seg_o, per_seg_p) = (j.w_orig.shape[0] / j.group_o, (j.ys.len() / j.group_p).max(1));
        let mo = mean_response(wo, j.ys.len(), cin_o, ntaps, |r| j.ys[r] / per_seg_o, &to);
        let mp = mean_response(&weight, j.ys.len(), cin_p, ntaps, |r| r / per_seg_p, &tp);
        let bias: Vec<f32> = (0..j.ys.len()).map(|r| (bias_o[r] as f64 + mo[r] - mp[r]) as f32).collect();
        Ok(finite(j, weight, bias, how))
    }
}

fn finite(j: &Job, weight: Vec<f32>, bias: Vec<f32>, how: Fit) -> Option<(Tensor, Tensor, Fit)> {
    weight.iter().chain(&bias).all(|v| v.is_finite()).then(|| (Tensor::f32(j.w_new.shape.clone(), weight), Tensor::f32(vec![j.ys.len()], bias), how))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tap_sums_count_zero_padding() {
        // 3x3 input of ones, 3x3 kernel, pad 1, stride 1: the centre tap sees 9 ones, corners 4.
        let ax = Axis { k: 3, stride: 1, dilation: 1, pad: 1, input: 3, output: 3 };
        let s = tap_sums(&[1.0; 9], 1, &[ax, ax]);
        assert_eq!(s, vec![4.0, 6.0, 4.0, 6.0, 9.0, 6.0, 4.0, 6.0, 4.0]);
    }
}
