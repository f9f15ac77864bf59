//! Quantization-aware recovery: the emitted QDQ model itself is the student. The torch
//! worker reads its QuantizeLinear / DequantizeLinear nodes as fake quantization with
//! straight-through rounding, and its int8 weights and int32 biases as float parameters in
//! integer units, rounded and clamped wherever they are read (`interpreter.Graph`, src/torch/); so the
//! forward it trains is the emitted model's (same scales, zero points, rounding, clipping,
//! layers kept float), and what comes back are new integers in the same initializers. The
//! float model (unpruned, or pruned and recovered) is the teacher, matched on the head
//! convolutions' logits as in `recover`; after pruning, the model before it can be instead
//! (`qat: {teacher: original}`), so training goes on recovering what pruning lost. Activation
//! scales stay those calibration chose, unless `scales` trains them too (LSQ: the fake
//! quantizer's gradient with respect to its step; a shared scale moves as one, and int32
//! biases follow their inputs' scales).

use crate::metrics::tensor_error::ErrorSums;
use crate::onnx::proto::ModelProto;
use crate::torch::schedule::Schedule;
use crate::torch::train::{self, Job, Outcome, Training};
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use ort::session::builder::GraphOptimizationLevel;
use std::collections::BTreeMap;

/// Weight of the YOLOv8 box edges' own error (each side's expected distance, in bins) beside
/// the DFL distributions' KL: INT8 moves the edges by fractions of a bin, which the KL barely
/// sees and IoU at 0.95 does.
pub const EDGE_WEIGHT: f64 = 1.0;

/// What both QAT passes train with: their schedule, no window or subset
/// (every weight of the whole frame), the box edges at `EDGE_WEIGHT`, and no class foreground
/// term (QAT was measured without it; `recover`'s default is for pruned students).
pub fn training(schedule: &Schedule, seed: u64) -> Training {
    Training { schedule: schedule.clone(), seed, window: None, trainable: None, box_edges: EDGE_WEIGHT, class_foreground: 0.0, v5_box_edges: 0.0, box_iou: 0.0, pseudo_labels: 0.0 }
}

pub struct Trained {
    /// The QDQ model with its trained integers.
    pub model: ModelProto,
    pub outcome: Outcome,
    /// rel L2 of each graph output of the written model on ONNX Runtime against the worker's
    /// fake-quantized forward, on the held-out frames: with ORT's reference kernels (float
    /// arithmetic on dequantized values, what the worker computes) and with its fused integer
    /// kernels; and the two kernel sets against each other, the floor of float noise in a
    /// quantized graph (a sum taken in another order lands a value on the other side of a
    /// rounding boundary now and then, and the step it takes travels to the outputs).
    pub reproduced: serde_json::Value,
}

/// The activation scale initializers of `quantized`, grouped by the value whose parameters
/// they take (`root`: a data-movement op's output takes its input's, and ONNX Runtime runs
/// such an op on integers only while the two stay equal). `dequantized` maps each quantized
/// value to its DequantizeLinear output, whose scale input is the initializer.
pub fn scale_groups(quantized: &ModelProto, dequantized: &BTreeMap<String, String>, root: impl Fn(&str) -> String) -> Vec<Vec<String>> {
    let Some(g) = quantized.graph.as_ref() else { return Vec::new() };
    let scale_of: std::collections::HashMap<&str, &str> = g.node.iter().filter(|n| n.op_type == "DequantizeLinear" && n.input.len() > 1).map(|n| (n.output[0].as_str(), n.input[1].as_str())).collect();
    let mut groups: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for (v, dq) in dequantized {
        if let Some(s) = scale_of.get(dq.as_str()) {
            groups.entry(root(v)).or_default().push(s.to_string());
        }
    }
    groups.into_values().collect()
}

/// What the worker trains: the head values it matches (`torch::heads::head_specs`, or
/// `torch::heads::split_head_specs` for a model from rknn-legalize), the weights' range, and
/// whether weights at the range's ends stay there (a toolchain that requantizes the
/// dequantized weights per channel by their peak then finds the same grid).
pub struct Student {
    pub heads: Vec<serde_json::Value>,
    /// Activation scale initializers that train, each group as one scale (empty: none do).
    pub scale_groups: Vec<Vec<String>>,
    /// Their step relative to the weights'.
    pub scale_lr: f64,
    /// The int8 weights' range: (-q, q) for symmetric `bits`-bit weights, (-128, 127) for
    /// asymmetric ones.
    pub weight_range: (i32, i32),
    pub pin_extremes: bool,
}

impl Student {
    /// Symmetric `bits`-bit weights.
    pub fn symmetric(heads: Vec<serde_json::Value>, bits: u32) -> Student {
        let q = (1i32 << (bits - 1)) - 1;
        Student { heads, scale_groups: Vec::new(), scale_lr: 1.0, weight_range: (-q, q), pin_extremes: false }
    }
}

/// Trains the integers of `quantized` (emitted from `float`) to reproduce `float`'s head
/// logits on `frames`; `held_out` (feeds of one image input) judge it, run on ONNX Runtime
/// with `threads`.
pub fn train(quantized: &ModelProto, float: &ModelProto, student: Student, frames: &[Tensor], held_out: &[Vec<(String, Tensor)>], o: &Training, threads: usize) -> Result<Trained> {
    let held: Vec<Tensor> = held_out.iter().map(|f| f[0].1.clone()).collect();
    // Steps relative to each tensor's largest magnitude: an int8 weight, an int32 bias (in
    // units thousands of times smaller) and a float layer's weight all move alike.
    let (qmin, qmax) = student.weight_range;
    let extra = serde_json::json!({"weight_qmin": qmin, "weight_qmax": qmax, "relative_lr": true, "pin_extremes": student.pin_extremes, "scale_groups": student.scale_groups, "scale_lr": student.scale_lr});
    let mut model = quantized.clone();
    let (outcome, fake_quant) = train::train(&mut model, float, frames, &held, o, Job { heads: student.heads, features: Vec::new(), extra, outputs: true, label: "qat" })?;
    let names: Vec<String> = model.graph.as_ref().map(|g| g.output.iter().map(|o| o.name.clone()).collect()).unwrap_or_default();
    let fake_quant: Vec<(String, Vec<f32>)> = names.into_iter().zip(fake_quant).map(|(n, t)| Ok((n, t.as_f32().ok_or_else(|| anyhow!("fake-quantized outputs are f32"))?.to_vec()))).collect::<Result<_>>()?;
    let reference = run_ort(&model, GraphOptimizationLevel::Disable, held_out, threads)?;
    let integer = run_ort(&model, GraphOptimizationLevel::Level3, held_out, threads)?;
    let reproduced = serde_json::json!({
        "reference_kernels": rel_l2(&fake_quant, &reference)?,
        "integer_kernels": rel_l2(&fake_quant, &integer)?,
        "reference_vs_integer_kernels": rel_l2(&reference, &integer)?,
    });
    Ok(Trained { model, outcome, reproduced })
}

/// `model`'s graph outputs on ORT at `level`, each with the frames stacked (as the worker's).
fn run_ort(model: &ModelProto, level: GraphOptimizationLevel, feeds: &[Vec<(String, Tensor)>], threads: usize) -> Result<Vec<(String, Vec<f32>)>> {
    let mut rt = OrtRuntime::with_options(model, level, threads)?;
    let mut stacked: Vec<(String, Vec<f32>)> = Vec::new();
    for feed in feeds {
        for (k, (name, t)) in rt.run(feed)?.into_iter().enumerate() {
            if stacked.len() <= k {
                stacked.push((name, Vec::new()));
            }
            stacked[k].1.extend(t.data.to_f64().into_iter().map(|v| v as f32));
        }
    }
    Ok(stacked)
}

/// rel L2 of each output of `candidate` against the same output of `reference`.
fn rel_l2(reference: &[(String, Vec<f32>)], candidate: &[(String, Vec<f32>)]) -> Result<BTreeMap<String, f64>> {
    if reference.len() != candidate.len() || reference.iter().zip(candidate).any(|(a, b)| a.1.len() != b.1.len()) {
        bail!("the QAT worker's outputs and ONNX Runtime's differ in number or size; this is a bug, please report it");
    }
    Ok(reference
        .iter()
        .zip(candidate)
        .map(|((name, a), (_, b))| {
            let mut s = ErrorSums::default();
            s.add(a.iter().map(|&v| v as f64), b.iter().map(|&v| v as f64));
            (name.clone(), s.finish().rel_l2)
        })
        .collect())
}
