//! QDQ emission at another toolchain's quantization points (RKNN-Toolkit2's, for
//! `rknn-qat`): a QuantizeLinear/DequantizeLinear pair on each named value with the given
//! int8 parameters, and nothing else quantized, so the QDQ model computes what that
//! toolchain's integer plan computes. Every convolution gets per-channel 8-bit weights as the
//! toolkit's `channel` method makes them, asymmetric over each channel's own min..max (zero
//! point per channel: measured against its simulator's dump of the first layer, this matches
//! all but 0.04% of the outputs, where symmetric max-abs weights miss 13% by one or two
//! steps), and, where its input is a point, an int32 bias at s_in·s_w; otherwise its bias
//! stays float.

use super::params::{quantize_bias, ActivationType, QParams};
use super::qdq::{add_qdq, dequantize_per_channel, node};
use crate::onnx::edit::{fresh_name, set_initializer};
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::{GraphProto, ModelProto};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, Result};
use std::collections::BTreeMap;

/// The int8 range of the toolkit's weights (w8a8).
pub const WEIGHT_RANGE: (i32, i32) = (-128, 127);

/// Per-channel asymmetric int8 weights over each channel's min..max: (values, scales, zero
/// points). A constant channel gets scale 1 around its value's integer.
pub fn asymmetric_weights(w: &[f32], out_channels: usize) -> (Vec<i8>, Vec<f64>, Vec<i8>) {
    let (qmin, qmax) = WEIGHT_RANGE;
    let per = (w.len() / out_channels.max(1)).max(1);
    let (mut values, mut scales, mut zps) = (Vec::with_capacity(w.len()), Vec::new(), Vec::new());
    for c in w.chunks(per) {
        let (lo, hi) = c.iter().filter(|v| v.is_finite()).fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v as f64), b.max(v as f64)));
        let s = if hi > lo && (hi - lo).is_finite() { (hi - lo) / (qmax - qmin) as f64 } else { 1.0 };
        let zp = if lo.is_finite() { (qmin as f64 - lo / s).round().clamp(qmin as f64, qmax as f64) } else { 0.0 };
        values.extend(c.iter().map(|&v| ((v as f64 / s).round() + zp).clamp(qmin as f64, qmax as f64) as i8));
        scales.push(s);
        zps.push(zp as i8);
    }
    (values, scales, zps)
}

/// The QDQ model for `model` with `points` (value -> int8 (scale, zero point)), and for each
/// point the value that holds its dequantized copy (a graph output keeps its name: the pair
/// is inserted before it).
pub fn emit(model: &ModelProto, points: &BTreeMap<String, (f64, i32)>) -> Result<(ModelProto, BTreeMap<String, String>)> {
    let src = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let mut g = src.clone();
    split_concat_convs(&mut g, points)?;
    let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
    let params = |v: &str| points.get(v).map(|&(scale, zero_point)| QParams { scale, zero_point, qmin: -128, qmax: 127 });
    let mut dequantized = BTreeMap::new();
    for v in points.keys() {
        let p = params(v).expect("a point");
        let dq = if outputs.contains(v) {
            // The producer writes a fresh value; the pair ends in the output's own name, which
            // its readers keep reading.
            let pre = fresh_name(&g, &format!("{v}_float"));
            for n in g.node.iter_mut() {
                n.output.iter_mut().filter(|x| *x == v).for_each(|x| *x = pre.clone());
            }
            add_qdq(&mut g, &pre, &p, ActivationType::I8);
            g.node.last_mut().expect("the DequantizeLinear just added").output[0] = v.clone();
            v.clone()
        } else {
            // Every reader so far reads the dequantized copy (the new QuantizeLinear, pushed
            // after them, reads the value itself).
            let readers = g.node.len();
            let dq = add_qdq(&mut g, v, &p, ActivationType::I8);
            for n in g.node[..readers].iter_mut() {
                n.input.iter_mut().filter(|x| *x == v).for_each(|x| *x = dq.clone());
            }
            dq
        };
        dequantized.insert(v.clone(), dq);
    }
    let initial: BTreeMap<String, Tensor> = g.initializer.iter().map(|t| Ok((t.name.clone(), to_tensor(t)?))).collect::<Result<_>>()?;
    for i in 0..g.node.len() {
        if g.node[i].op_type != "Conv" {
            continue;
        }
        let n = g.node[i].clone();
        let Some(w) = n.input.get(1).and_then(|w| initial.get(w)).filter(|w| w.as_f32().is_some()) else { continue };
        let out_channels = w.shape[0];
        let (values, scales, zero_points) = asymmetric_weights(w.as_f32().expect("f32"), out_channels);
        let w_name = fresh_name(&g, &format!("{}_int8", n.input[1]));
        set_initializer(&mut g, from_tensor(&w_name, &Tensor::new(w.shape.clone(), TensorData::I8(values))));
        g.node[i].input[1] = dequantize_per_channel(&mut g, &w_name, &scales, TensorData::I8(zero_points), 0);
        // The input a point feeds (its dequantized copy) fixes the bias scale.
        let input_point = points.iter().find(|(v, _)| dequantized.get(*v) == Some(&n.input[0])).map(|(_, p)| p.0);
        let bias = n.input.get(2).filter(|b| !b.is_empty()).and_then(|b| initial.get(b)).and_then(|b| b.as_f32());
        if let (Some(s_in), Some(b)) = (input_point, bias) {
            let (values, scales, _) = quantize_bias(b, s_in, &scales);
            let b_name = fresh_name(&g, &format!("{}_bias_int32", if n.name.is_empty() { "conv" } else { &n.name }));
            set_initializer(&mut g, from_tensor(&b_name, &Tensor::new(vec![out_channels], TensorData::I32(values))));
            g.node[i].input[2] = dequantize_per_channel(&mut g, &b_name, &scales, TensorData::I32(vec![0; out_channels]), 0);
        }
    }
    // The float weights and biases the integers replaced.
    let read: std::collections::HashSet<String> = g.node.iter().flat_map(|n| n.input.iter().cloned()).chain(g.output.iter().chain(&g.input).map(|v| v.name.clone())).collect();
    g.initializer.retain(|t| read.contains(&t.name));
    sort_topologically(&mut g)?;
    let mut out = model.clone();
    out.graph = Some(g);
    Ok((out, dequantized))
}

/// The Concat → Conv pairs that RKNN-Toolkit2 computes as one convolution per concatenated
/// input, summed: it lists a point `<input>_conv` for each input, and rounds each partial sum
/// there (its simulator's dumps show an Add where the convolution was).
pub struct Splits {
    /// The partial sums' names (points of their own).
    pub sums: Vec<String>,
    /// The split convolutions' outputs (each now an Add's).
    pub outputs: Vec<String>,
}

/// The splits of `g`; `has_point` says whether the toolkit lists a name.
pub fn splits(g: &GraphProto, has_point: impl Fn(&str) -> bool) -> Splits {
    let pairs = splittable(g, &has_point);
    Splits {
        sums: pairs.iter().flat_map(|&(c, _)| g.node[c].input.iter().map(|x| format!("{x}_conv"))).collect(),
        outputs: pairs.iter().map(|&(_, k)| g.node[k].output[0].clone()).collect(),
    }
}

/// (Concat, Conv) node pairs to split: the Concat's only reader is a plain convolution of it,
/// and every input has its partial-sum point.
fn splittable(g: &GraphProto, has_point: &dyn Fn(&str) -> bool) -> Vec<(usize, usize)> {
    let mut pairs = Vec::new();
    for (c, n) in g.node.iter().enumerate().filter(|(_, n)| n.op_type == "Concat") {
        if !matches!(crate::onnx::attr::int(n, "axis", 0), 1 | -3) || !n.input.iter().all(|x| has_point(&format!("{x}_conv"))) {
            continue;
        }
        let readers: Vec<usize> = (0..g.node.len()).filter(|&k| g.node[k].input.contains(&n.output[0])).collect();
        if let [k] = readers[..] {
            let conv = &g.node[k];
            if conv.op_type == "Conv" && conv.input[0] == n.output[0] && crate::onnx::attr::int(conv, "group", 1) == 1 {
                pairs.push((c, k));
            }
        }
    }
    pairs
}

/// Rewrites each splittable Concat → Conv into per-input convolutions `<conv>_part<i>`
/// writing `<input>_conv` (the weights' input channels cut at the Concat's offsets; the bias
/// on the last part, as the toolkit's simulator dumps show), summed by Adds into the
/// convolution's output.
fn split_concat_convs(g: &mut GraphProto, points: &BTreeMap<String, (f64, i32)>) -> Result<()> {
    let pairs = splittable(g, &|v| points.contains_key(v));
    if pairs.is_empty() {
        return Ok(());
    }
    let graph = crate::ir::Graph::build(g)?;
    let inf = crate::ir::infer(&graph);
    let mut added = Vec::new();
    for &(c, k) in &pairs {
        let (concat, conv) = (g.node[c].clone(), g.node[k].clone());
        let w = to_tensor(g.initializer.iter().find(|t| t.name == conv.input[1]).ok_or_else(|| anyhow!("'{}' has no constant weights", conv.name))?)?;
        let wv = w.as_f32().ok_or_else(|| anyhow!("'{}' weights are not f32", conv.name))?;
        let (out_ch, in_ch, per_in) = (w.shape[0], w.shape[1], w.shape[2..].iter().product::<usize>());
        let mut offset = 0;
        let mut parts = Vec::new();
        for (i, x) in concat.input.iter().enumerate() {
            let ci = inf.shape(x).and_then(|s| s.get(1).copied()).ok_or_else(|| anyhow!("the channel count of '{x}' is unknown"))?;
            if offset + ci > in_ch {
                anyhow::bail!("'{}' reads more channels than its weights have", conv.name);
            }
            let part: Vec<f32> = (0..out_ch).flat_map(|o| wv[(o * in_ch + offset) * per_in..(o * in_ch + offset + ci) * per_in].iter().copied()).collect();
            let mut shape = w.shape.clone();
            shape[1] = ci;
            let w_name = fresh_name(g, &format!("{}_part{i}", conv.input[1]));
            set_initializer(g, from_tensor(&w_name, &Tensor::f32(shape, part)));
            let mut inputs = vec![x.clone(), w_name];
            if i + 1 == concat.input.len() {
                inputs.extend(conv.input.get(2).cloned());
            }
            let out = format!("{x}_conv");
            added.push(node("Conv", &format!("{}_part{i}", conv.name), inputs, vec![out.clone()], conv.attribute.clone()));
            parts.push(out);
            offset += ci;
        }
        let mut sum = parts[0].clone();
        for (i, p) in parts.iter().enumerate().skip(1) {
            let out = if i + 1 == parts.len() { conv.output[0].clone() } else { fresh_name(g, &format!("{}_sum{i}", conv.output[0])) };
            added.push(node("Add", &format!("{}_sum{i}", conv.name), vec![sum, p.clone()], vec![out.clone()], vec![]));
            sum = out;
        }
    }
    let gone: std::collections::HashSet<usize> = pairs.iter().flat_map(|&(c, k)| [c, k]).collect();
    let kept: Vec<_> = std::mem::take(&mut g.node).into_iter().enumerate().filter(|(i, _)| !gone.contains(i)).map(|(_, n)| n).collect();
    g.node = kept;
    g.node.extend(added);
    Ok(())
}

/// `float` with each convolution's weights and bias replaced by the dequantized integers of
/// the same-named node in `quantized` (emitted by [`emit`], then trained): what a toolchain
/// that quantizes float weights per channel over their min..max turns back into the same
/// integers, as long as every channel keeps an integer at each end of the range.
pub fn dequantized_weights(float: &ModelProto, quantized: &ModelProto) -> Result<ModelProto> {
    let q = quantized.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let inits: BTreeMap<&str, &crate::onnx::proto::TensorProto> = q.initializer.iter().map(|t| (t.name.as_str(), t)).collect();
    let producer: BTreeMap<&str, &crate::onnx::proto::NodeProto> = q.node.iter().flat_map(|n| n.output.iter().map(move |o| (o.as_str(), n))).collect();
    // A DequantizeLinear's value: integers less zero points, times scales (per channel, axis 0).
    let dequantize = |v: &str| -> Result<Option<Vec<f32>>> {
        let Some(dq) = producer.get(v).filter(|n| n.op_type == "DequantizeLinear") else { return Ok(None) };
        let (Some(x), Some(s)) = (inits.get(dq.input[0].as_str()), inits.get(dq.input[1].as_str())) else { return Ok(None) };
        let (x, s) = (to_tensor(x)?, to_tensor(s)?);
        let s = s.as_f32().ok_or_else(|| anyhow!("a weight scale is not f32"))?;
        let zp = match dq.input.get(2).and_then(|z| inits.get(z.as_str())) {
            Some(z) => to_tensor(z)?.data.to_f64(),
            None => vec![0.0; s.len()],
        };
        let per = (x.len() / s.len().max(1)).max(1);
        Ok(Some(x.data.to_f64().iter().enumerate().map(|(k, &v)| ((v - zp[k / per]) * s[k / per] as f64) as f32).collect()))
    };
    // A trained parameter's float value: dequantized integers, or a float parameter (a bias
    // behind no point) as it is.
    let trained_value = |v: &str| -> Result<Option<Vec<f32>>> {
        if let Some(d) = dequantize(v)? {
            return Ok(Some(d));
        }
        match inits.get(v) {
            Some(init) => Ok(Some(to_tensor(init)?.as_f32().ok_or_else(|| anyhow!("'{v}' is not f32"))?.to_vec())),
            None => Ok(None),
        }
    };
    let mut out = float.clone();
    let g = out.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?;
    let trained: BTreeMap<&str, &crate::onnx::proto::NodeProto> = q.node.iter().filter(|n| n.op_type == "Conv").map(|n| (n.name.as_str(), n)).collect();
    let convs: Vec<(String, Vec<String>)> = g.node.iter().filter(|n| n.op_type == "Conv").map(|n| (n.name.clone(), n.input.clone())).collect();
    for (name, inputs) in convs {
        let Some(t) = trained.get(name.as_str()) else {
            // A convolution split per concatenated input: its parts' weights, side by side.
            let parts: Vec<&&crate::onnx::proto::NodeProto> = (0..).map_while(|i| trained.get(format!("{name}_part{i}").as_str())).collect();
            if parts.is_empty() {
                anyhow::bail!("convolution '{name}' is missing from the trained model");
            }
            let mut weights = Vec::new();
            for p in &parts {
                weights.push(trained_value(&p.input[1])?.ok_or_else(|| anyhow!("'{}' has no weights", p.name))?);
            }
            let old = to_tensor(g.initializer.iter().find(|i| i.name == inputs[1]).ok_or_else(|| anyhow!("'{}' is not an initializer", inputs[1]))?)?;
            let out_ch = old.shape[0];
            let joined: Vec<f32> = (0..out_ch).flat_map(|o| weights.iter().flat_map(move |w| w[o * w.len() / out_ch..(o + 1) * w.len() / out_ch].iter().copied())).collect();
            set_initializer(g, from_tensor(&inputs[1], &Tensor::f32(old.shape, joined)));
            if let (Some(b), Some(pb)) = (inputs.get(2).filter(|b| !b.is_empty()), parts.last().and_then(|p| p.input.get(2))) {
                if let Some(v) = trained_value(pb)? {
                    set_initializer(g, from_tensor(b, &Tensor::f32(vec![v.len()], v)));
                }
            }
            continue;
        };
        for slot in 1..inputs.len().min(3) {
            let Some(values) = trained_value(&t.input[slot])? else { continue };
            let old = g.initializer.iter().find(|i| i.name == inputs[slot]).ok_or_else(|| anyhow!("'{}' is not an initializer", inputs[slot]))?;
            let shape = to_tensor(old)?.shape;
            set_initializer(g, from_tensor(&inputs[slot], &Tensor::f32(shape, values)));
        }
    }
    Ok(out)
}
