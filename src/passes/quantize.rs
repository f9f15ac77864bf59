//! `quantize`: post-training INT8 in QDQ form, calibrated on camera (or simulated) frames.
//!
//! Needs: a float detection graph with constant weights and one image input (the lossless
//! passes first; prune before it if wanted); opset >= 13; for `rounding: learned` and `qat`,
//! PyTorch (the cache's torch venv, installed on first use) and, for `qat`, a YOLOv5 or YOLOv8 head
//! (and, for `qat: {teacher: original}`, a `prune` earlier in the recipe, without a scene ROI).
//! Guarantees: outputs keep names, shapes and float type; the head convolutions' outputs and
//! the decode after them stay float (boxes and scores never share a scale); every scale is
//! finite and positive, whatever the frames (a constant or all-zero activation gets a fixed
//! scale and a warning).
//! Reports: the range method and frames, warnings, the rounding (learned: each layer's output
//! error with nearest and learned rounding), every quantized layer's error against
//! float alone and accumulated (worst first), the bias shifts corrected (`measured_bias`: the
//! shifts it measured and what was left after), the layers mixed
//! precision kept float and why, the layers `float_where_faster` timed (and kept float where
//! ONNX Runtime ran the model faster so), quantization-aware recovery (`qat`: its training, the output
//! error before and after, the written model on ONNX Runtime against the worker's
//! fake-quantized forward), and the outputs' error per channel group on held-out frames
//! (and under each of `calib_conditions`, the stress conditions mixed into calibration).

use crate::calib_frames::{image_feeds, image_feeds_from};
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use crate::clock::Clock;
use crate::quant::attribution::{self, worst_rel_l2, LayerError};
use crate::quant::collect::{statistics, Statistics};
use crate::quant::params::{degenerate_range, quantize_weights, weight_rounding_shift, ActivationType, QParams};
use crate::quant::plan::{plan, Plan};
use crate::quant::qdq::{emit, EmitOptions};
use crate::quant::range::{choose, Method};
use crate::torch::schedule::Schedule;
use anyhow::{anyhow, bail, Result};
use std::collections::{BTreeSet, HashMap, HashSet};

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// How activation ranges are chosen: `mse` (the clip with the least expected squared error),
    /// `minmax`, `percentile`, `entropy` (KL, as TensorRT).
    pub method: Method,
    /// Kept fraction for `percentile`, in percent.
    pub percentile: f64,
    /// Activation type: `u8` (ONNX Runtime's fast path on x86) or `i8`.
    pub activations: ActivationType,
    /// 8, or 7 for ONNX Runtime on AVX2 without VNNI (its u8s8 kernels sum product pairs in
    /// int16, which full-range 8-bit weights saturate).
    pub weight_bits: u32,
    /// Frames whose activations set the ranges.
    pub calib_frames: usize,
    /// Frames (of the calibration set) for bias correction, error attribution and mixed precision.
    pub analysis_frames: usize,
    /// Further frames, never used to calibrate, on which the result is measured.
    pub held_out_frames: usize,
    /// Subtract the per-channel output mean shift that weight rounding causes (from the
    /// calibration frames' per-channel input means).
    pub bias_correction: bool,
    /// Bias correction measured on the emitted INT8 model: every quantized convolution's
    /// per-channel output mean shift against float on the analysis frames, level by level
    /// from the input, which also takes in what the activations' rounding and clipping
    /// upstream moved (`quant::output_bias`). False: weight rounding's shift alone.
    pub measured_bias: bool,
    /// Largest rel L2 of any output channel group against float; layers are kept float,
    /// most sensitive first, until it holds. None: no mixed precision.
    pub error_budget: Option<f64>,
    /// At most this many layers kept in float by the error budget's search.
    pub max_float_layers: usize,
    /// Nodes (or their output values) to leave in float.
    pub keep_float: Vec<String>,
    /// Convolutions with fewer output channels per group than this stay float, with the
    /// element-wise nodes that read only them and the nodes that read them directly
    /// (`quant::narrow`): ONNX Runtime's integer convolution is slower than its float one
    /// there. 0: every layer is a candidate.
    pub narrow_float: usize,
    /// The detector's last convolutions, and the nodes writing what they read, stay float
    /// (`quant::head_inputs`): rounding the activation a YOLOv8 box convolution reads moves
    /// its DFL box edges by fractions of a bin, which mAP at high IoU sees (on the trained v8:
    /// agreement with float 0.966 -> 0.990). About 1% of the MACs.
    pub float_head_inputs: bool,
    /// After mixed precision: keep float the heavy convolutions ONNX Runtime runs the model
    /// faster without quantizing, timed on this machine (`quant::speed`). The choice follows the
    /// compiling machine; `keep_float` pins one.
    pub float_where_faster: bool,
    /// Seed of the simulated calibration frames (when no `--calib`).
    pub seed: u64,
    /// `qdq` (ONNX Runtime fuses it) or `qlinear` (convolutions as QLinearConv, for tract).
    pub format: Format,
    /// Stress conditions (names from `passes/stress.yaml`) mixed into the calibration set:
    /// calibration frame i is clean when i % (n + 1) == 0, else under condition i % (n + 1) - 1,
    /// so ranges cover what the deployment will meet. The held-out check runs under each.
    pub calib_conditions: Vec<String>,
    /// `nearest`, or `learned`: each convolution weight's rounding direction chosen to
    /// reproduce its layer's float output (AdaRound, in the torch worker; replaces bias
    /// correction on those layers, whose mean shift it already minimizes).
    pub rounding: Rounding,
    /// Learned rounding: optimizer steps per convolution.
    pub rounding_iterations: usize,
    /// Learned rounding: calibration frames it reconstructs (the last of them).
    pub rounding_frames: usize,
    /// Quantization-aware recovery after emission (and mixed precision): the emitted model's
    /// integers trained on the calibration frames to match the float model. None: off.
    #[serde(deserialize_with = "super::some_over_defaults")]
    pub qat: Option<Qat>,
    /// Past these, on the held-out frames against float, the INT8 model is broken rather than
    /// less accurate: the compile fails (exit 1) and writes no artifact.
    pub hard_limit: HardLimit,
}

/// The hard limit of a lossy result: any output group's rel L2 above `max_rel_l2` or cosine
/// below `min_cosine` against float. A rel L2 of 1 is an output as far from float as zeros
/// are; a cosine of 0.9 is boxes and scores pointing elsewhere. The error budget aims well
/// inside them (0.1 in the shipped recipes).
#[derive(serde::Deserialize, serde::Serialize, Clone, Copy, Debug)]
#[serde(deny_unknown_fields, default)]
pub struct HardLimit {
    /// Past this rel L2 from float on held-out frames, the INT8 model is broken: no artifact, exit
    /// 1.
    pub max_rel_l2: f64,
    /// Below this cosine with float on held-out frames, likewise.
    pub min_cosine: f64,
}

impl Default for HardLimit {
    fn default() -> Self {
        HardLimit { max_rel_l2: 1.0, min_cosine: 0.9 }
    }
}

/// Quantization-aware recovery's schedule (`qat: {minutes: 5}`). Unknown keys are refused
/// where options are read (`passes::with`, through [`super::over_defaults`]).
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct Qat {
    #[serde(flatten)]
    pub schedule: Schedule,
    /// Training frames: the calibration frames, and more drawn after the held-out ones up to
    /// this count (0 or fewer than the calibration frames: those alone). A hundred epochs
    /// over 64 frames fit those frames; on the trained v8, 512 frames moved the held-out error
    /// from the classes to the boxes and left mAP where it was (README), so the default is 0.
    pub frames: usize,
    /// What the quantized model learns to reproduce: `float`, the quantize pass's input, or
    /// `original`, the model before an earlier `prune` (QAT then goes on recovering what
    /// pruning lost instead of stopping at the pruned float model's accuracy).
    pub teacher: QatTeacher,
    /// Activation scales train too (LSQ), at `scale_lr` times the weights' relative step;
    /// values that share parameters (a data-movement op's input and output) share one scale,
    /// and each int32 bias is requantized to its input's new scale.
    pub scales: bool,
    /// With `scales: true`: the activation scales' step, relative to the weights' step.
    pub scale_lr: f64,
    /// Weight of the YOLOv8 box edges' own error beside the DFL's KL; default: 1 from `float`
    /// (`qat::EDGE_WEIGHT`), recovery's 16 from `original`.
    pub box_edges: Option<f64>,
    /// Weight of the class scores' KL on the cells where the teacher sees an object; default:
    /// none from `float`, recovery's 4 from `original`. Above 0, the held-out distillation
    /// loss decides whether the training is kept (the class scores' rel L2 is ruled by the
    /// background cells that this term deliberately weighs less).
    pub class_foreground: Option<f64>,
}

#[derive(serde::Serialize, serde::Deserialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum QatTeacher {
    #[default]
    Float,
    Original,
}

impl Default for Qat {
    fn default() -> Self {
        Qat { schedule: Schedule::new(800, 1e-4, 8), frames: 0, teacher: QatTeacher::Float, scales: false, scale_lr: 1.0, box_edges: None, class_foreground: None }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Rounding {
    Nearest,
    Learned,
}

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    Qdq,
    Qlinear,
}

impl Options {
    /// The ranges, checked when the recipe loads (calibration and QAT take minutes).
    pub fn check(&self) -> Result<()> {
        if !(2..=8).contains(&self.weight_bits) {
            bail!("weight_bits {} must be between 2 and 8", self.weight_bits);
        }
        if !(50.0..=100.0).contains(&self.percentile) {
            bail!("percentile {} must be between 50 and 100", self.percentile);
        }
        if self.error_budget.is_some_and(|b| !(b >= 0.0 && b.is_finite())) {
            bail!("error_budget must be a number, 0 or more");
        }
        let HardLimit { max_rel_l2, min_cosine } = self.hard_limit;
        if !(max_rel_l2 > 0.0 && max_rel_l2.is_finite()) || !(-1.0..=1.0).contains(&min_cosine) {
            bail!("hard_limit needs max_rel_l2 > 0 and min_cosine in [-1, 1]");
        }
        if let Some(q) = &self.qat {
            q.schedule.check("qat: ")?;
            if !(q.scale_lr > 0.0 && q.scale_lr.is_finite()) {
                bail!("qat: scale_lr must be a positive number");
            }
            if [q.box_edges, q.class_foreground].iter().flatten().any(|w| !(*w >= 0.0 && w.is_finite())) {
                bail!("qat's box_edges and class_foreground must be finite and 0 or more");
            }
        }
        Ok(())
    }
}

impl Default for Options {
    fn default() -> Self {
        Options {
            method: Method::Mse,
            percentile: 99.99,
            activations: ActivationType::U8,
            weight_bits: 8,
            calib_frames: 64,
            analysis_frames: 8,
            held_out_frames: 8,
            bias_correction: true,
            measured_bias: false,
            error_budget: None,
            max_float_layers: 8,
            keep_float: Vec::new(),
            narrow_float: 0,
            float_head_inputs: false,
            float_where_faster: false,
            seed: 0,
            format: Format::Qdq,
            calib_conditions: Vec::new(),
            rounding: Rounding::Nearest,
            rounding_iterations: 400,
            rounding_frames: 16,
            qat: None,
            hard_limit: HardLimit::default(),
        }
    }
}

pub struct Quantize {
    pub options: Options,
}

/// A layer mixed precision tries stays float only if the worst output error drops below this
/// fraction of what it was.
const MIN_IMPROVEMENT: f64 = 0.97;

/// Windows per learned-rounding step (48x48 outputs each, see `rounding::CROP`): 18k output
/// positions to average over, few enough that a step on 2 cores takes milliseconds.
const ROUNDING_BATCH: usize = 8;

/// Layers listed in the report's attribution table (worst first); the rest are counted.
const REPORTED_LAYERS: usize = 40;

impl Pass for Quantize {
    fn name(&self) -> &'static str {
        "quantize"
    }

    fn check(&self) -> Result<()> {
        self.options.check()
    }

    fn needs(&self) -> Vec<super::Capability> {
        match &self.options.qat {
            Some(q) if q.teacher == QatTeacher::Original => vec![super::Capability::Teacher],
            _ => Vec::new(),
        }
    }

    /// The blocks are quantized as they run (four times wider: integer kernels take them);
    /// the torch interpreter (QAT, learned rounding) has no SpaceToDepth and gets them lowered.
    fn takes_space_to_depth(&self) -> bool {
        self.options.qat.is_none() && self.options.rounding == Rounding::Nearest
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let o = &self.options;
        let original = match &o.qat {
            Some(q) if q.teacher == QatTeacher::Original => Some(original_teacher(cx)?),
            _ => None,
        };
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let float = model.clone();
        let g = float.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        let mut clock = Clock::default();
        let (mut feeds, source) = image_feeds(&graph, &inf, cx.calib.as_deref(), o.calib_frames.max(1) + o.held_out_frames, o.seed)?;
        let calib = o.calib_frames.max(1);
        // Held-out frames come after the calibration frames; a folder too small for both
        // measures on its last calibration frames, and the report says so.
        let (held_out, overlap) = if feeds.len() > calib { (feeds.split_off(calib), false) } else { (feeds.iter().rev().take(o.held_out_frames.max(1)).cloned().collect(), true) };
        let conditions = crate::optics::conditions::by_name(&o.calib_conditions)?;
        if let Some(c) = conditions.iter().find(|c| c.changes_blur()) {
            bail!("calib_conditions: '{}' changes the blur map, which the quantized model has folded in; pick conditions that change frames", c.name);
        }
        mix_conditions(&mut feeds, &conditions, o.seed);
        let analysis: Vec<_> = feeds.iter().take(o.analysis_frames.max(1)).cloned().collect();

        clock.lap("frames");
        let narrow = crate::quant::narrow::narrow_float(&graph, o.narrow_float);
        let head_inputs = if o.float_head_inputs { crate::quant::head_inputs::head_inputs(&graph) } else { Default::default() };
        let keep: HashSet<String> = o.keep_float.iter().cloned().chain(narrow.keys().cloned()).chain(head_inputs.keys().cloned()).collect();
        let base = plan(&graph, &keep);
        let values: Vec<String> = base.quantized_values(&graph).into_iter().collect();
        // A sigmoid's output range follows from its input's (it is monotonic), and a
        // data-movement output uses its input's parameters (Plan::root), so those large
        // tensors need not be read back from the runtime.
        let mut collected: Vec<String> = values.iter().map(|v| base.root(v)).map(|v| sigmoid_input(&graph, v).unwrap_or_else(|| v.to_string())).collect();
        collected.sort();
        collected.dedup();
        let conv_inputs: HashMap<String, usize> = base
            .quantized
            .iter()
            .map(|&i| graph.node(i))
            .filter(|n| n.op_type == "Conv")
            .filter_map(|n| Some((n.input[0].clone(), inf.shape(&n.input[0])?.get(1).copied()?)))
            .collect();
        let conv_inputs = if o.bias_correction { conv_inputs } else { HashMap::new() };
        let stats = statistics(&float, &collected, &conv_inputs, &feeds, threads)?;
        let (params, mut warnings) = activation_params(&graph, &base, &values, &stats, o);
        let mut shifts = if o.bias_correction { bias_shifts(&graph, &base, &stats.channel_means, o.weight_bits)? } else { HashMap::new() };
        clock.lap("ranges");
        let learned = match o.rounding {
            Rounding::Nearest => None,
            Rounding::Learned => {
                // The last calibration frames: the first ones judge mixed precision, which
                // must not see the frames the rounding was fitted to.
                let frames: Vec<crate::tensor::Tensor> = feeds.iter().rev().take(o.rounding_frames.max(1)).map(|f| f[0].1.clone()).collect();
                let opts = crate::quant::rounding::Options { activations: o.activations, weight_bits: o.weight_bits, iterations: o.rounding_iterations, batch: ROUNDING_BATCH, seed: o.seed };
                let l = crate::quant::rounding::learn(&float, &graph, &base, &params, &frames, &opts)?;
                shifts.retain(|i, _| !l.weights.contains_key(i));
                Some(l)
            }
        };
        let no_weights = HashMap::new();
        let weights = learned.as_ref().map_or(&no_weights, |l| &l.weights);
        clock.lap("rounding");
        let measured_bias = if o.measured_bias {
            let (emitted, _) = emit(&float, &base, &EmitOptions { params: &params, activations: o.activations, weight_bits: o.weight_bits, bias_shift: &shifts, weights })?;
            Some(crate::quant::output_bias::correct(&float, &graph, &base, &mut shifts, emitted, &analysis, threads)?)
        } else {
            None
        };
        clock.lap("measured_bias");
        let collection = collection_cost(&float, &feeds, &stats, threads)?;
        clock.lap("plain_inference_for_comparison");

        let emit_with = |p: &Plan| emit(&float, p, &EmitOptions { params: &params, activations: o.activations, weight_bits: o.weight_bits, bias_shift: &shifts, weights });
        let (quantized, emitted) = emit_with(&base)?;
        clock.lap("emit");
        let alone = attribution::alone(&float, &base, &params, o.activations, o.weight_bits, &analysis, threads)?;
        clock.lap("layer_analysis");

        let mixed = match o.error_budget {
            Some(budget) => mixed_precision(&MixedPrecision { float: &float, quantized: &quantized, graph: &graph, keep: &keep, layers: &alone.layers, frames: &analysis, threads, budget, max_layers: o.max_float_layers }, &emit_with)?,
            None => Mixed { names: keep.clone(), ..Mixed::default() },
        };
        let (current, (quantized, emitted)) = match mixed.chosen {
            Some(chosen) => chosen,
            None => (base.clone(), (quantized, emitted)),
        };
        clock.lap("mixed_precision");
        let (current, (quantized, emitted), speed) = if o.float_where_faster {
            let search = crate::quant::speed::Search { graph: &graph, keep: &mixed.names, feed: &held_out[0], threads };
            let found = crate::quant::speed::float_where_faster(&search, &current, &quantized, &emit_with)?;
            let chosen = found.chosen.unwrap_or((current, (quantized, emitted)));
            (chosen.0, chosen.1, Some(found.report))
        } else {
            (current, (quantized, emitted), None)
        };
        clock.lap("float_where_faster");
        // QAT measures the model it keeps on the held-out frames; those errors are reported below.
        // The errors QAT measured against its teacher (the float model, or the original).
        let (quantized, qat, kept_errors) = match &o.qat {
            None => (quantized, None, None),
            Some(q) => {
                // Frames beyond the calibration set come after the held-out ones (the same
                // draw, continued), so training never sees a frame that judges it.
                let wanted = crate::calib_frames::affordable_frames("qat", &graph, &inf, q.frames);
                let drawn = calib + held_out.len();
                let more = if wanted > calib && !overlap { image_feeds_from(&graph, &inf, cx.calib.as_deref(), drawn, wanted - calib, o.seed)?.0 } else { Vec::new() };
                let train = feeds.iter().map(|f| f[0].1.clone()).chain(more.into_iter().filter_map(|f| f.into_iter().next().map(|(_, t)| t))).collect();
                let groups = if q.scales { crate::quant::qat::scale_groups(&quantized, &emitted.dequantized, |v| current.root(v).to_string()) } else { Vec::new() };
                let (model, report, errors) = quantization_aware(&float, original.as_ref(), quantized, train, &held_out, o, q, groups, threads, cx)?;
                (model, Some(report), Some(errors))
            }
        };
        clock.lap("qat");
        let accumulated = attribution::accumulated(&float, &quantized, &emitted.dequantized, &analysis, threads)?;
        let mut layers = alone.layers.clone();
        for l in &mut layers {
            l.accumulated = accumulated.get(&l.value).copied();
        }
        layers.retain(|l| current.quantized.contains(&alone.node_of_value[&l.value]));
        layers.sort_by(|a, b| b.accumulated.map_or(b.alone.rel_l2, |e| e.rel_l2).total_cmp(&a.accumulated.map_or(a.alone.rel_l2, |e| e.rel_l2)));
        clock.lap("accumulated_errors");
        let (outputs, from_original) = match (kept_errors, original.is_some()) {
            (Some(errors), false) => (errors, None),
            (errors, _) => (attribution::output_errors(&float, &quantized, &held_out, threads, None)?, errors),
        };
        // QAT from the original moves the model away from the pruned float one, towards the
        // original: it is broken only when past the limit against both.
        let (judged, against) = match &from_original {
            Some(e) => (e, "the unpruned original"),
            None => (&outputs, "float"),
        };
        if from_original.as_ref().is_none_or(|e| check_hard_limit(e, &layers, held_out.len(), against, o.hard_limit).is_err()) {
            check_hard_limit(&outputs, &layers, held_out.len(), "float", o.hard_limit)?;
        }
        if let Some(budget) = o.error_budget {
            let worst = worst_rel_l2(judged);
            if worst > budget {
                warnings.push(format!(
                    "INT8 missed its error budget: its worst output group is rel L2 {worst:.3} from {against} on {} held-out frames (budget {budget}, hard limit {}), so its detections will move; calibrate on frames like the deployment's (--calib), raise max_float_layers ({}), or add qat to get closer",
                    held_out.len(),
                    o.hard_limit.max_rel_l2,
                    o.max_float_layers
                ));
            }
        }
        let mut stressed = Vec::new();
        for c in &conditions {
            let frames: Vec<Vec<(String, crate::tensor::Tensor)>> = held_out.iter().enumerate().map(|(i, f)| f.iter().map(|(n, t)| (n.clone(), c.apply_tensor(t, o.seed ^ (i as u64 + 1) << 20))).collect()).collect();
            let e = attribution::output_errors(&float, &quantized, &frames, threads, None)?;
            stressed.push(serde_json::json!({ "condition": c.name, "worst_output_rel_l2": worst_rel_l2(&e) }));
        }
        if emitted.biases_clamped > 0 {
            warnings.push(format!("{} int32 bias values were clamped (input x weight scale too small for the bias)", emitted.biases_clamped));
        }
        // What ONNX Runtime makes of it: QLinearConv etc. where it fused, Conv where it did not.
        let ort_ops = crate::runtime::ort_runtime::OrtRuntime::optimized_ops(&quantized)?;
        *model = quantized;
        crate::ir::rewrite::dce::eliminate(super::graph_mut(model)?)?;
        let qlinear_convs = if o.format == Format::Qlinear { Some(crate::quant::qlinear::to_qlinear_conv(super::graph_mut(model)?)?) } else { None };
        clock.lap("held_out_check");
        for w in warnings {
            cx.warn(w);
        }
        let float_nodes: Vec<serde_json::Value> = current.float.iter().map(|(&i, why)| serde_json::json!({"node": g.node[i].name, "op": g.node[i].op_type, "why": why})).collect();
        Ok(serde_json::json!({
            "method": o.method,
            "percentile": (o.method == Method::Percentile).then_some(o.percentile),
            "activations": o.activations,
            "weight_bits": o.weight_bits,
            "format": o.format,
            "qlinear_convolutions": qlinear_convs,
            "calibration": source,
            "calibration_frames": feeds.len(),
            "analysis_frames": analysis.len(),
            "held_out_frames": held_out.len(),
            "held_out_overlaps_calibration": overlap,
            "bias_corrected_convolutions": shifts.len(),
            "measured_bias": measured_bias,
            "rounding": learned.map_or(serde_json::json!({"method": "nearest"}), |l| l.report),
            "qat": qat,
            "emitted": emitted,
            "ort_optimized_ops": ort_ops,
            "mixed_precision": { "error_budget": o.error_budget, "kept_float": mixed.kept, "tried_and_rejected": mixed.rejected, "note": mixed.warning },
            "hard_limit": o.hard_limit,
            "float_where_faster": speed,
            "narrow_float": narrow.iter().map(|(node, why)| serde_json::json!({"node": node, "why": why})).collect::<Vec<_>>(),
            "float_head_inputs": head_inputs.iter().map(|(node, why)| serde_json::json!({"node": node, "why": why})).collect::<Vec<_>>(),
            "float_nodes": float_nodes,
            "output_errors": outputs,
            "worst_output_rel_l2": worst_rel_l2(&outputs),
            "calib_conditions": o.calib_conditions,
            "held_out_under_conditions": stressed,
            "collection": collection,
            "seconds": clock.laps,
            "calibrate_and_emit_seconds": clock.laps["frames"] + clock.laps["ranges"] + clock.laps["emit"],
            "layers_quantized": layers.len(),
            "layers": layers.iter().take(REPORTED_LAYERS).collect::<Vec<_>>(),
        }))
    }
}

/// Refuses a result past the hard limit, naming the worst output groups and layers.
fn check_hard_limit(outputs: &[attribution::OutputError], layers: &[LayerError], frames: usize, against: &str, limit: HardLimit) -> Result<()> {
    // As worst_rel_l2 judges: a decoded output by its groups, any other output whole.
    let grouped: HashSet<&str> = outputs.iter().filter(|e| e.group.is_some()).map(|e| e.output.as_str()).collect();
    let broken: Vec<String> = outputs
        .iter()
        .filter(|e| e.group.is_some() || !grouped.contains(e.output.as_str()))
        .filter(|e| !(e.error.rel_l2 <= limit.max_rel_l2) || !(e.error.cosine >= limit.min_cosine))
        .map(|e| format!("{}{} (rel L2 {:.3}, cosine {:.3})", e.output, e.group.map_or(String::new(), |g| format!(" {g}")), e.error.rel_l2, e.error.cosine))
        .collect();
    if broken.is_empty() {
        return Ok(());
    }
    let worst: Vec<String> = layers.iter().take(3).map(|l| format!("{} ({:.3})", l.node, l.accumulated.map_or(l.alone.rel_l2, |e| e.rel_l2))).collect();
    Err(super::QualityFailure(format!(
        "INT8 broke the model: {} against {against} on {frames} held-out frames, past the hard limit (rel L2 {}, cosine {}); worst layers: {}. Calibrate on frames like the model's input (--calib), keep those layers float (keep_float), or raise hard_limit if this is expected",
        broken.join(", "),
        limit.max_rel_l2,
        limit.min_cosine,
        worst.join(", ")
    ))
    .into())
}

/// The model before an earlier `prune`, for `qat: {teacher: original}`: the same frames
/// reach both models, so a scene crop (whose teacher sees full frames) is refused.
fn original_teacher(cx: &PassContext) -> Result<super::Teacher> {
    let t = cx.teacher.clone().ok_or_else(|| anyhow!("qat's `teacher: original` distills from the model before pruning: put a prune pass before quantize, or use `teacher: float`"))?;
    if t.window.is_some() {
        bail!("qat's `teacher: original` does not take a scene ROI (the original sees full frames, the quantized model their crop); use `teacher: float`");
    }
    Ok(t)
}

/// Quantization-aware recovery of `quantized` on `frames` (the calibration frames and any
/// more) towards `float`, or towards `original` (the model before pruning, with the head rows
/// a scene kept); the trained model is kept only if it got closer to its teacher on the
/// held-out frames (the worst output group's rel L2; with a class foreground term, from
/// `original` by default, the distillation loss, below).
/// Returns the model kept, the report, and the kept model's held-out output errors against
/// its teacher.
#[allow(clippy::too_many_arguments)]
fn quantization_aware(float: &ModelProto, original: Option<&super::Teacher>, quantized: ModelProto, frames: Vec<crate::tensor::Tensor>, held_out: &[Vec<(String, crate::tensor::Tensor)>], o: &Options, q: &Qat, scale_groups: Vec<Vec<String>>, threads: usize, cx: &mut PassContext) -> Result<(ModelProto, serde_json::Value, Vec<attribution::OutputError>)> {
    if frames.len() < q.schedule.batch {
        bail!("qat has {} calibration frames for batches of {}; raise calib_frames or lower qat's batch", frames.len(), q.schedule.batch);
    }
    let mut schedule = crate::quant::qat::training(&q.schedule, o.seed);
    let (teacher, view, heads) = match original {
        None => (float, None, crate::torch::heads::head_specs(float)?),
        Some(t) => {
            // Going on from recovery: its terms for a pruned student, on the head's logits
            // only (its neck features too scored 0.7900 against 0.8027 on the pruned v8, README).
            let r = super::recover::Options::default();
            (schedule.box_edges, schedule.class_foreground) = (r.box_edges, r.class_foreground);
            (&t.model, crate::scene::compare::SceneView::of_teacher(float, &t.model)?, crate::torch::heads::head_specs_against(float, &t.kept)?)
        }
    };
    schedule.box_edges = q.box_edges.unwrap_or(schedule.box_edges);
    schedule.class_foreground = q.class_foreground.unwrap_or(schedule.class_foreground);
    // The term weighs YOLOv8 class heads only (`torch::train::weigh_terms`).
    let foreground = schedule.class_foreground > 0.0 && heads.iter().any(|h| h["kind"] == "v8cls");
    let student = crate::quant::qat::Student { scale_groups, scale_lr: q.scale_lr, ..crate::quant::qat::Student::symmetric(heads, o.weight_bits) };
    let t = crate::quant::qat::train(&quantized, teacher, student, &frames, held_out, &schedule, threads)?;
    cx.record_training(&t.outcome);
    let reference = attribution::ReferenceOutputs::new(teacher, held_out, threads, view.as_ref())?;
    let (before, after) = (reference.errors(&quantized)?, reference.errors(&t.model)?);
    // Class scores differ most on the background cells, which rel L2 sums over and mAP does
    // not rank. Against the unpruned model (v8 w0.25 pruned to 0.28: classes 0.245 -> 0.260
    // while mAP rose 0.7795 -> 0.7947), and wherever the foreground term trades background
    // for objects (the unpruned v8: 0.052 -> 0.083 while mAP rose from plain INT8's 0.8459 to
    // 0.8515), the distillation loss, which weighs the objects' cells, judges the training.
    let by_loss = original.is_some() || foreground;
    let kept = if by_loss { t.outcome.held_out_loss_after < t.outcome.held_out_loss_before } else { worst_rel_l2(&after) < worst_rel_l2(&before) };
    let report = serde_json::json!({
        "kept": kept,
        "kept_by": if by_loss { "held_out_distillation_loss" } else { "worst_output_rel_l2" },
        "box_edges": schedule.box_edges,
        "class_foreground": schedule.class_foreground,
        "teacher": if original.is_some() { "original" } else { "float" },
        "frames": frames.len(),
        "held_out_frames": held_out.len(),
        "output_rel_l2": { "before": super::prune::by_name(&before), "after": super::prune::by_name(&after) },
        "emitted_vs_fake_quant_rel_l2": t.reproduced,
        "not_reproducible": t.outcome.not_reproducible(),
        "training": t.outcome,
    });
    // Against the model it learned from: the float model, or the original before pruning.
    let errors = if kept { after } else { before };
    Ok((if kept { t.model } else { quantized }, report, errors))
}

/// Frames timed plainly to put the range collection's cost in proportion (the first of the
/// same frames, threads and session options; run to run, a plain 640x480 frame varies by
/// ~1%, so 16 give the mean well within the noise of the ratio).
const PLAIN_TIMED_FRAMES: usize = 16;

/// What range collection cost per frame against the float model's plain inference.
fn collection_cost(float: &ModelProto, feeds: &[Vec<(String, crate::tensor::Tensor)>], stats: &Statistics, threads: usize) -> Result<serde_json::Value> {
    let n = feeds.len().max(1) as f64;
    let plain = crate::quant::collect::plain_seconds_per_frame(float, feeds, threads, PLAIN_TIMED_FRAMES)?;
    let per_frame = stats.seconds / n;
    Ok(serde_json::json!({
        "frames": feeds.len(),
        "threads": threads,
        "ms_per_frame": per_frame * 1e3,
        "statistics_ms_per_frame": stats.statistics_seconds / n * 1e3,
        "plain_inference_ms_per_frame": plain * 1e3,
        "plain_frames_timed": feeds.len().min(PLAIN_TIMED_FRAMES),
        "ratio_to_plain_inference": if plain > 0.0 { per_frame / plain } else { 0.0 },
    }))
}

/// Puts calibration frame i under condition i % (n + 1) - 1 (frame 0 and every (n + 1)-th
/// stay clean). Only the image input changes; it is the feeds' only input.
fn mix_conditions(feeds: &mut [Vec<(String, crate::tensor::Tensor)>], conditions: &[crate::optics::conditions::Condition], seed: u64) {
    let n = conditions.len() + 1;
    for (i, f) in feeds.iter_mut().enumerate().filter(|(i, _)| i % n != 0) {
        for (_, t) in f.iter_mut() {
            *t = conditions[i % n - 1].apply_tensor(t, seed ^ i as u64);
        }
    }
}

/// Activation parameters of every quantized value from its statistics, and warnings about
/// degenerate or non-finite data.
fn activation_params(graph: &Graph, plan: &Plan, values: &[String], stats: &Statistics, o: &Options) -> (HashMap<String, QParams>, Vec<String>) {
    let mut warnings = Vec::new();
    let mut params = HashMap::new();
    // Roots first: a data-movement output takes its root's parameters, in this plan and in
    // any mixed-precision plan that leaves the data movement in float.
    let roots: BTreeSet<&str> = values.iter().map(|v| plan.root(v)).collect();
    for &v in &roots {
        let (lo, hi, h) = match sigmoid_input(graph, v) {
            Some(input) => {
                let h = &stats.histograms[&input];
                let sigmoid = |x: f64| if x.is_finite() { 1.0 / (1.0 + (-x).exp()) } else { 0.0 };
                (0.0, if h.is_empty() { 0.0 } else { sigmoid(h.max) }, h)
            }
            None => {
                let h = &stats.histograms[v];
                let (lo, hi) = choose(h, o.method, o.percentile, o.activations);
                (lo, hi, h)
            }
        };
        if h.non_finite > 0 {
            warnings.push(format!("'{v}' had {} NaN/infinite values on the calibration frames; they were ignored", h.non_finite));
        }
        if degenerate_range(lo, hi) {
            warnings.push(format!("'{v}' is constant zero on the calibration frames; it gets a fixed scale {:.6}", QParams::activation(lo, hi, o.activations).scale));
        }
        params.insert(v.to_string(), QParams::activation(lo, hi, o.activations));
    }
    for v in values {
        let p = params[plan.root(v)];
        params.insert(v.clone(), p);
    }
    (params, warnings)
}

/// The input of the Sigmoid producing `v`, if one does.
fn sigmoid_input(graph: &Graph, v: &str) -> Option<String> {
    graph.producer_of(v).filter(|n| n.op_type == "Sigmoid").map(|n| n.input[0].clone())
}

struct MixedPrecision<'a> {
    float: &'a ModelProto,
    /// The model with every plannable layer quantized (where the search starts).
    quantized: &'a ModelProto,
    graph: &'a Graph<'a>,
    keep: &'a HashSet<String>,
    layers: &'a [LayerError],
    frames: &'a [Vec<(String, crate::tensor::Tensor)>],
    threads: usize,
    budget: f64,
    max_layers: usize,
}

#[derive(Default)]
struct Mixed {
    /// The plan and model with the kept layers float (None: nothing kept).
    chosen: Option<(Plan, (ModelProto, crate::quant::qdq::Emitted))>,
    kept: Vec<serde_json::Value>,
    rejected: Vec<serde_json::Value>,
    warning: Option<String>,
    /// Every node float in the chosen plan by name (keep_float and the layers kept).
    names: HashSet<String>,
}

/// Mixed precision: layers go float one at a time, largest alone error first, until the
/// worst output group is within the budget; a layer stays float only if it clearly helps.
fn mixed_precision(m: &MixedPrecision, emit_with: &dyn Fn(&Plan) -> Result<(ModelProto, crate::quant::qdq::Emitted)>) -> Result<Mixed> {
    let mut ranked: Vec<&LayerError> = m.layers.iter().collect();
    ranked.sort_by(|a, b| b.alone.rel_l2.total_cmp(&a.alone.rel_l2));
    let reference = attribution::ReferenceOutputs::new(m.float, m.frames, m.threads, None)?;
    let mut worst = worst_rel_l2(&reference.errors(m.quantized)?);
    let mut names = m.keep.clone();
    let mut out = Mixed::default();
    for layer in ranked.into_iter().take(m.max_layers) {
        if worst <= m.budget {
            break;
        }
        let mut with = names.clone();
        with.insert(layer.node.clone());
        let candidate_plan = plan(m.graph, &with);
        let candidate = emit_with(&candidate_plan)?;
        let after = worst_rel_l2(&reference.errors(&candidate.0)?);
        let step = serde_json::json!({"node": layer.node, "op": layer.op, "alone_rel_l2": layer.alone.rel_l2, "output_rel_l2_before": worst, "output_rel_l2_after": after});
        // A float layer costs speed: keep it only where it clearly helps.
        if after < worst * MIN_IMPROVEMENT {
            (names, worst) = (with, after);
            out.chosen = Some((candidate_plan, candidate));
            out.kept.push(step);
        } else {
            out.rejected.push(step);
        }
    }
    out.names = names;
    if worst > m.budget {
        out.warning = Some(format!("error budget {} not met: worst output rel L2 {worst:.4} with {} layers float after trying {} (max_float_layers {})", m.budget, out.kept.len(), out.kept.len() + out.rejected.len(), m.max_layers));
    }
    Ok(out)
}

/// Per quantized convolution, the output mean shift its weight rounding causes (subtracted
/// from its bias at emission).
fn bias_shifts(g: &Graph, p: &Plan, means: &HashMap<String, Vec<f64>>, bits: u32) -> Result<HashMap<usize, Vec<f64>>> {
    let mut out = HashMap::new();
    for &i in &p.quantized {
        let n = g.node(i);
        let Some(mean) = (n.op_type == "Conv").then(|| means.get(&n.input[0])).flatten() else { continue };
        let w = crate::onnx::tensor_proto::to_tensor(g.initializers[n.input[1].as_str()])?;
        let v = w.as_f32().expect("planned");
        let q = quantize_weights(v, w.shape[0], bits);
        let group = crate::onnx::attr::int(n, "group", 1).max(1) as usize;
        out.insert(i, weight_rounding_shift(v, &w.shape, group, &q, mean));
    }
    Ok(out)
}
