//! Learned rounding (AdaRound) of convolution weights: each weight goes to the grid point
//! below or above its float value, whichever makes its layer's output on the quantized
//! model's input closest to the float layer's, learned in the cache's torch worker
//! (`src/torch/rounding.py`, through the torch interpreter). The worker sees the
//! emitted model's exact quantizers (activation scales and zero points, constant operands,
//! per-channel weight scales); only the integers come back, so emission is otherwise unchanged.

use super::params::{ActivationType, QParams, QuantizedWeights};
use super::plan::Plan;
use crate::ir::Graph;
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::to_tensor;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::collections::HashMap;


pub struct Options {
    /// The emitted model's activation type and weight bits.
    pub activations: ActivationType,
    pub weight_bits: u32,
    /// Optimizer steps per convolution.
    pub iterations: usize,
    /// Windows per step, each from a frame drawn from those given.
    pub batch: usize,
    pub seed: u64,
}

/// Adam's step on the rounding variables: ten times BRECQ's 1e-3, which is meant for 20k
/// steps; here a few hundred must move a variable across its grid interval.
const LR: f64 = 1e-2;
/// Weight of the regularizer that pushes every rounding variable to 0 or 1, against the
/// layer's output error relative to its own scale (so one weight serves every layer).
const REGULARIZER: f64 = 0.01;
/// Fraction of the steps before the regularizer starts: the variables first move freely.
const WARMUP: f64 = 0.2;
/// Side of the output windows a step reconstructs (each cut from a padded frame, so it equals
/// the full convolution there): a full-resolution 256x192 layer costs 1/20 of a whole frame
/// per window, and deep layers smaller than this are taken whole.
const CROP: usize = 48;

pub struct Learned {
    /// Node index -> its learned int8 weights and their (unchanged) per-channel scales.
    pub weights: HashMap<usize, QuantizedWeights>,
    pub report: serde_json::Value,
}

/// Learns the rounding of every quantized convolution of `float` under `plan`, on `frames`.
pub fn learn(float: &ModelProto, graph: &Graph, plan: &Plan, params: &HashMap<String, QParams>, frames: &[Tensor], o: &Options) -> Result<Learned> {
    let (ty, bits) = (o.activations, o.weight_bits);
    let json = |p: &QParams| serde_json::json!({"scale": p.scale, "zero_point": p.zero_point, "qmin": p.qmin, "qmax": p.qmax});
    let mut activations = serde_json::Map::new();
    for v in plan.quantized_values(graph) {
        if let Some(p) = params.get(plan.root(&v)) {
            activations.insert(v, json(p));
        }
    }
    // Head convolutions are measured through what the decode makes of them (scores through a
    // sigmoid, DFL boxes through their softmax); a model whose head is not recognized
    // measures them raw.
    let heads: HashMap<String, serde_json::Value> = crate::torch::heads::head_specs(float)
        .unwrap_or_default()
        .into_iter()
        .filter_map(|h| {
            let post = match h["kind"].as_str()? {
                "v8box" => serde_json::json!({"kind": "dfl", "reg_max": h["reg_max"]}),
                _ => serde_json::json!({"kind": "sigmoid"}),
            };
            Some((h["value"].as_str()?.to_string(), post))
        })
        .collect();
    let mut constants = serde_json::Map::new();
    let mut layers = Vec::new();
    let mut nodes = Vec::new();
    for &i in &plan.quantized {
        let n = graph.node(i);
        for s in Plan::activation_slots(graph, i) {
            if let Some(t) = graph.initializers.get(n.input[s].as_str()) {
                let values = to_tensor(t)?;
                let v = values.as_f32().ok_or_else(|| anyhow!("constant '{}' is not f32", n.input[s]))?;
                constants.insert(n.input[s].clone(), json(&QParams::covering(v, ty)));
            }
        }
        if n.op_type != "Conv" {
            continue;
        }
        let w = to_tensor(graph.initializers[n.input[1].as_str()])?;
        let nearest = super::params::quantize_weights(w.as_f32().expect("planned"), w.shape[0], bits);
        let post = heads.get(n.output[0].as_str()).cloned().unwrap_or_else(|| activation_after(graph, &n.output[0]));
        layers.push(serde_json::json!({"node": n.name, "scales": nearest.scales, "qmax": (1i32 << (bits - 1)) - 1, "post": post}));
        nodes.push((i, nearest.scales, w.shape.clone()));
    }
    if nodes.iter().map(|(i, ..)| &graph.node(*i).name).collect::<std::collections::HashSet<_>>().len() != nodes.len() {
        bail!("learned rounding needs named, distinct convolution nodes; run the cleanup pass first");
    }
    let work = tempfile::tempdir()?;
    let dir = work.path();
    crate::onnx::save(float, &dir.join("model.onnx"))?;
    crate::torch::train::write_frames(frames, &dir.join("frames.npy"))?;
    let out = dir.join("learned");
    std::fs::create_dir(&out)?;
    let config = serde_json::json!({
        "model": dir.join("model.onnx"), "frames": dir.join("frames.npy"), "out": out,
        "layers": layers, "activations": activations, "constants": constants,
        "iterations": o.iterations, "batch": o.batch, "seed": o.seed, "lr": LR, "weight": REGULARIZER, "warmup": WARMUP, "crop": CROP,
    });
    let config_path = dir.join("config.json");
    std::fs::write(&config_path, serde_json::to_vec(&config)?)?;
    let pb = ProgressBar::new(nodes.len() as u64);
    pb.set_style(ProgressStyle::with_template("learned rounding [{bar:30}] {pos}/{len} layers, {msg} ({elapsed})").expect("valid template").progress_chars("=> "));
    let done = crate::torch::run(dir, "rounding.py", &[config_path.as_os_str()], 1, |e| {
        if e["event"] == "layer" {
            pb.set_position(e["done"].as_u64().unwrap_or(0));
            pb.set_message(format!("{}: error {:.4} -> {:.4}", e["node"].as_str().unwrap_or("?"), e["rel_mse_nearest"].as_f64().unwrap_or(f64::NAN), e["rel_mse_learned"].as_f64().unwrap_or(f64::NAN)));
        }
    })?;
    pb.finish_and_clear();
    let qmax = ((1i32 << (bits - 1)) - 1) as f32;
    let mut weights = HashMap::new();
    for (k, (i, scales, shape)) in nodes.into_iter().enumerate() {
        let a = crate::optics::npy::read(&out.join(format!("w{k}.npy")))?;
        if a.shape != shape || a.data.iter().any(|&q| q.fract() != 0.0 || q.abs() > qmax) {
            bail!("the rounding worker returned weights for '{}' that are not integers within ±{qmax} of shape {shape:?}; this is a bug, please report it", graph.node(i).name);
        }
        weights.insert(i, QuantizedWeights { values: a.data.iter().map(|&q| q as i8).collect(), scales });
    }
    Ok(Learned { weights, report: summarize(done) })
}

/// The activation that reads a convolution's output alone (SiLU as Sigmoid and Mul, or
/// ReLU), through which the worker measures its error; none otherwise.
fn activation_after(graph: &Graph, value: &str) -> serde_json::Value {
    let mut ops: Vec<&str> = graph.consumers_of(value).iter().map(|&i| graph.node(i).op_type.as_str()).collect();
    ops.sort_unstable();
    match ops.as_slice() {
        ["Mul", "Sigmoid"] => serde_json::json!({"kind": "silu"}),
        ["Relu"] => serde_json::json!({"kind": "relu"}),
        _ => serde_json::Value::Null,
    }
}

/// The worker's account, with the mean error ratio (learned / nearest) over layers first.
fn summarize(done: serde_json::Value) -> serde_json::Value {
    let layers = done["layers"].as_array().cloned().unwrap_or_default();
    let ratios: Vec<f64> = layers.iter().filter_map(|l| Some(l["rel_mse_learned"].as_f64()? / l["rel_mse_nearest"].as_f64()?.max(1e-30))).collect();
    serde_json::json!({
        "method": "learned",
        "layers": layers.len(),
        "mean_error_ratio_learned_to_nearest": ratios.iter().sum::<f64>() / ratios.len().max(1) as f64,
        "layers_improved": ratios.iter().filter(|&&r| r < 1.0).count(),
        "seconds": done["seconds"],
        "device": done["device"],
        "torch": done["torch"],
        "per_layer": layers,
    })
}
