//! Bias correction measured on the outputs: each quantized convolution's per-channel output
//! mean in the emitted INT8 model against the float model's, on the frames it is given (the
//! `quantize` pass's analysis frames), subtracted from its bias. Weight rounding's shift is
//! predicted from the input means (`params::weight_rounding_shift`); this one also takes in
//! what the activations' rounding and clipping upstream moved (an `mse` range clips a tail,
//! and every layer after it sees its mean move).
//!
//! Level by level, from the input: a convolution's shift is measured once every convolution
//! before it is corrected. Correcting all of them from one measurement counts the upstream
//! layers' share twice (once where it arose, once downstream), and repeating that diverged
//! on the trained v8 (the second round's shifts four times the first's).

use super::collect::statistics;
use super::plan::Plan;
use crate::ir::Graph;
use crate::onnx::edit::{initializer, set_initializer};
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Result};
use std::collections::HashMap;

/// What it measured, in the outputs' own units.
#[derive(Debug, Default, serde::Serialize)]
pub struct Report {
    /// Levels (convolutions with no convolution between them and the input are level 0).
    pub levels: usize,
    pub convolutions: usize,
    pub mean_abs_shift: f64,
    pub largest_abs_shift: f64,
    pub largest_at: String,
    /// Measured again on the corrected model: what is left is the int32 biases' rounding and
    /// float noise.
    pub residual_mean_abs_shift: f64,
    pub residual_largest_abs_shift: f64,
}

/// Adds each planned convolution's measured shift into `shifts` (by node index, subtracted
/// from the bias at emission); `emitted` is the INT8 model under `shifts` as they were.
pub fn correct(
    float: &ModelProto,
    graph: &Graph,
    plan: &Plan,
    shifts: &mut HashMap<usize, Vec<f64>>,
    emitted: ModelProto,
    feeds: &[Vec<(String, Tensor)>],
    threads: usize,
) -> Result<Report> {
    let levels = levels(graph, plan);
    let channels: HashMap<String, usize> = levels.iter().flatten().map(|(v, _, c)| (v.clone(), *c)).collect();
    if channels.is_empty() {
        return Ok(Report::default());
    }
    let reference = statistics(float, &[], &channels, feeds, threads)?.channel_means;
    // Each level's shifts go into its int32 biases in place (the caller emits the model it
    // keeps from `shifts`, which rounds each bias once).
    let mut model = emitted;
    let mut r = Report { levels: levels.len(), convolutions: channels.len(), ..Report::default() };
    let (mut shifted, mut left) = (Vec::new(), Vec::new());
    // Run k corrects level k and reads what is left at level k - 1, corrected in the run
    // before. A convolution read out runs in float on its dequantized inputs; ONNX Runtime
    // fuses everything else into its integer kernels, as a deployment runs them (their
    // rounding moves the means downstream by as much as the shifts corrected here, so the
    // model is never read out whole). Level k - 1's convolutions, read out in run k, then
    // quantize their float outputs themselves: a code differs from the fused kernel's here and
    // there, without moving the means after it (measured on the tiny v5).
    for k in 0..=levels.len() {
        let now = levels.get(k).map_or(&[][..], |l| &l[..]);
        let before = k.checked_sub(1).map_or(&[][..], |j| &levels[j][..]);
        let wanted: HashMap<String, usize> = now.iter().chain(before).map(|(v, _, c)| (v.clone(), *c)).collect();
        let measured = statistics(&model, &[], &wanted, feeds, threads)?.channel_means;
        let diff = |v: &String| -> Vec<f64> { measured.get(v).zip(reference.get(v)).map_or(Vec::new(), |(q, f)| q.iter().zip(f).map(|(q, f)| q - f).collect()) };
        for (v, _, _) in before {
            left.extend(diff(v).into_iter().filter(|d| d.is_finite()).map(f64::abs));
        }
        for (v, node, c) in now {
            let shift = shifts.entry(*node).or_insert_with(|| vec![0.0; *c]);
            let d: Vec<f64> = diff(v).into_iter().map(|d| if d.is_finite() { d } else { 0.0 }).collect();
            for (s, d) in shift.iter_mut().zip(&d) {
                *s += d;
                shifted.push(d.abs());
                if d.abs() > r.largest_abs_shift {
                    (r.largest_abs_shift, r.largest_at) = (d.abs(), v.clone());
                }
            }
            lower_bias(&mut model, v, &d)?;
        }
    }
    let mean = |x: &[f64]| x.iter().sum::<f64>() / x.len().max(1) as f64;
    r.mean_abs_shift = mean(&shifted);
    r.residual_mean_abs_shift = mean(&left);
    r.residual_largest_abs_shift = left.iter().copied().fold(0.0, f64::max);
    Ok(r)
}

/// Subtracts `shift` (per output channel, in the output's units) from the int32 bias of the
/// convolution writing `output` in the emitted model, at its DequantizeLinear's scales.
fn lower_bias(model: &mut ModelProto, output: &str, shift: &[f64]) -> Result<()> {
    let g = model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?;
    let conv = g.node.iter().find(|n| n.op_type == "Conv" && n.output.first().is_some_and(|o| o == output)).ok_or_else(|| anyhow!("no convolution writes '{output}'"))?;
    let dq = conv.input.get(2).and_then(|b| g.node.iter().find(|n| n.op_type == "DequantizeLinear" && n.output[0] == *b)).ok_or_else(|| anyhow!("'{output}': its bias is not a DequantizeLinear"))?;
    let (values, scales) = (dq.input[0].clone(), dq.input[1].clone());
    let scale = to_tensor(initializer(g, &scales).ok_or_else(|| anyhow!("'{output}': no bias scale"))?)?.data.to_f64();
    let mut bias = to_tensor(initializer(g, &values).ok_or_else(|| anyhow!("'{output}': no int32 bias"))?)?;
    let TensorData::I32(b) = &mut bias.data else { bail!("'{output}': the bias is not int32") };
    for (k, (b, d)) in b.iter_mut().zip(shift).enumerate() {
        let s = scale.get(k).or(scale.first()).copied().unwrap_or(1.0);
        *b = (*b as f64 - d / s).round().clamp(i32::MIN as f64, i32::MAX as f64) as i32;
    }
    set_initializer(g, from_tensor(&values, &bias));
    Ok(())
}

/// The planned convolutions by level, each as (output, node, channels): a level's
/// convolutions read nothing a convolution of the same or a later level writes.
fn levels(graph: &Graph, plan: &Plan) -> Vec<Vec<(String, usize, usize)>> {
    // Per value: how many planned convolutions lie on the longest path from the inputs to it.
    let mut depth: HashMap<&str, usize> = HashMap::new();
    let mut out: Vec<Vec<(String, usize, usize)>> = Vec::new();
    for &i in &graph.order {
        let n = graph.node(i);
        let before = n.input.iter().filter_map(|v| depth.get(v.as_str())).copied().max().unwrap_or(0);
        // A planned convolution's weights are an initializer; its output channels come first.
        let channels = (n.op_type == "Conv" && plan.quantized.contains(&i)).then(|| graph.initializers.get(n.input.get(1)?.as_str())?.dims.first().map(|&c| c as usize)).flatten();
        let after = match channels {
            Some(c) => {
                if out.len() <= before {
                    out.resize_with(before + 1, Vec::new);
                }
                out[before].push((n.output[0].clone(), i, c));
                before + 1
            }
            None => before,
        };
        for o in &n.output {
            depth.insert(o.as_str(), after);
        }
    }
    out
}
