//! Rewriting the graph for a pruning plan: every tensor that indexes a pruned channel loses
//! that index. Weights are sliced into fresh initializers (an original may be shared by a
//! node that keeps its channels); Split sizes, channel Slices, Resize sizes and declared
//! shapes follow.

use crate::analysis::channels::ChannelAnalysis;
use crate::onnx::attr;
use crate::onnx::edit::{fresh_name, initializer, set_initializer, set_input_constant};
use crate::onnx::proto::{AttributeProto, DimensionValue, GraphProto, TypeValue};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Result};
use std::collections::HashMap;

/// Kept channel positions of every value that loses channels.
pub fn kept_positions(a: &ChannelAnalysis, keep: &[bool]) -> Result<HashMap<String, Vec<usize>>> {
    let mut out = HashMap::new();
    for (v, s) in &a.values {
        let kept: Vec<usize> = (0..s.channels).filter(|&i| keep[a.class_of[s.offset + i]]).collect();
        if kept.is_empty() {
            bail!("pruning would remove every channel of '{v}'; lower the ratio or protect it");
        }
        if kept.len() < s.channels {
            out.insert(v.clone(), kept);
        }
    }
    Ok(out)
}

/// Applies the kept positions to `g`. Returns the number of initializers rewritten.
pub fn apply(g: &mut GraphProto, a: &ChannelAnalysis, kept: &HashMap<String, Vec<usize>>, opset: i64) -> Result<usize> {
    let mut rewritten = 0;
    for i in 0..g.node.len() {
        let n = g.node[i].clone();
        let k = |v: &str| kept.get(v);
        let out0 = n.output.first().map(String::as_str).unwrap_or("");
        match n.op_type.as_str() {
            "Conv" | "ConvTranspose" => {
                let (x, y) = (k(&n.input[0]), k(out0));
                if x.is_none() && y.is_none() {
                    continue;
                }
                let w = constant(g, &n.input[1])?;
                let group = attr::int(&n, "group", 1).max(1) as usize;
                let cin = if n.op_type == "Conv" { w.shape[1] * group } else { w.shape[0] };
                let cout = if n.op_type == "Conv" { w.shape[0] } else { w.shape[1] * group };
                let xs: Vec<usize> = x.cloned().unwrap_or_else(|| (0..cin).collect());
                let ys: Vec<usize> = y.cloned().unwrap_or_else(|| (0..cout).collect());
                let (new_w, new_group) = slice_conv_weight(&n.op_type, &w, group, &xs, &ys)?;
                set_input_constant(g, i, 1, &new_w, "pruned");
                rewritten += 1;
                if let Some(b) = n.input.get(2).filter(|s| !s.is_empty()) {
                    if y.is_some() {
                        let bt = constant(g, b)?.select(0, &ys).ok_or_else(|| anyhow!("bias of {} does not match its channels", n.name))?;
                        set_input_constant(g, i, 2, &bt, "pruned");
                        rewritten += 1;
                    }
                }
                if new_group != group {
                    set_int(&mut g.node[i], "group", new_group as i64);
                }
            }
            "BatchNormalization" => {
                if let Some(ys) = k(out0) {
                    for p in 1..5 {
                        let t = constant(g, &n.input[p])?.select(0, ys).ok_or_else(|| anyhow!("BatchNorm {} parameters do not match", n.name))?;
                        set_input_constant(g, i, p, &t, "pruned");
                        rewritten += 1;
                    }
                }
            }
            "Split" => {
                if let Some(xs) = k(&n.input[0]) {
                    let channels = a.values.get(&n.input[0]).map_or(0, |s| s.channels);
                    let old = split_sizes(g, &n, channels)?;
                    let mut at = 0;
                    let sizes: Vec<i64> = old
                        .iter()
                        .map(|&s| {
                            let c = xs.iter().filter(|&&x| x >= at && x < at + s).count() as i64;
                            at += s;
                            c
                        })
                        .collect();
                    set_split(g, i, sizes, opset)?;
                    rewritten += 1;
                }
            }
            "Slice" => {
                if let Some(xs) = k(&n.input[0]) {
                    let channels = a.values.get(&n.input[0]).map_or(0, |s| s.channels);
                    rewritten += rewrite_slice(g, i, xs, channels)?;
                }
            }
            "Resize" | "Upsample" => {
                if let (Some(ys), Some(sz)) = (k(out0), n.input.get(3).filter(|s| !s.is_empty())) {
                    let mut v = constant(g, sz)?.as_i64s().ok_or_else(|| anyhow!("Resize sizes of {} are not integers", n.name))?;
                    if v.len() == 4 {
                        v[1] = ys.len() as i64;
                        set_input_constant(g, i, 3, &Tensor::new(vec![4], TensorData::I64(v)), "pruned");
                        rewritten += 1;
                    }
                }
            }
            _ => {
                // Broadcast element-wise ops: per-channel constants follow the output.
                if let Some(ys) = k(out0) {
                    for (p, name) in n.input.iter().enumerate() {
                        let Some(t) = initializer(g, name) else { continue };
                        let r = t.dims.len();
                        if r >= 3 && t.dims[r - 3] > 1 {
                            let sliced = to_tensor(t)?.select(r - 3, ys).ok_or_else(|| anyhow!("constant '{name}' of {} does not match its channels", n.name))?;
                            set_input_constant(g, i, p, &sliced, "pruned");
                            rewritten += 1;
                        }
                    }
                }
            }
        }
    }
    for v in g.value_info.iter_mut().chain(g.output.iter_mut()) {
        if let Some(ks) = kept.get(&v.name) {
            if let Some(TypeValue::TensorType(t)) = v.r#type.as_mut().and_then(|t| t.value.as_mut()) {
                if let Some(d) = t.shape.as_mut().and_then(|s| s.dim.get_mut(1)) {
                    d.value = Some(DimensionValue::DimValue(ks.len() as i64));
                }
            }
        }
    }
    Ok(rewritten)
}

fn constant(g: &GraphProto, name: &str) -> Result<Tensor> {
    to_tensor(initializer(g, name).ok_or_else(|| anyhow!("'{name}' is not a constant"))?)
}

fn set_int(n: &mut crate::onnx::proto::NodeProto, name: &str, v: i64) {
    match n.attribute.iter_mut().find(|a| a.name == name) {
        Some(a) => a.i = Some(v),
        None => n.attribute.push(AttributeProto { name: name.into(), r#type: 2, i: Some(v), ..Default::default() }),
    }
}

/// The weight for kept input positions `xs` and output positions `ys`, and the new group count.
fn slice_conv_weight(op: &str, w: &Tensor, group: usize, xs: &[usize], ys: &[usize]) -> Result<(Tensor, usize)> {
    let bad = || anyhow!("cannot slice a {op} weight of shape {:?} (group {group})", w.shape);
    if group == 1 {
        let (rows, cols) = if op == "Conv" { (ys, xs) } else { (xs, ys) };
        return Ok((w.select(0, rows).and_then(|t| t.select(1, cols)).ok_or_else(bad)?, 1));
    }
    let depthwise = w.shape[1] == 1 && xs.len() == ys.len() && w.shape[0] == group;
    if depthwise {
        // Input and output channels are coupled: one row per kept channel.
        return Ok((w.select(0, ys).ok_or_else(bad)?, ys.len()));
    }
    if op != "Conv" {
        return Err(bad());
    }
    // Grouped: rows by output, then per row the kept inputs of its segment (same count in
    // every segment; the plan guaranteed it).
    let (cout, per_in) = (w.shape[0], w.shape[1]);
    let per_out = cout / group;
    let rows = w.select(0, ys).ok_or_else(bad)?;
    let taps: usize = w.shape[2..].iter().product();
    let src = rows.as_f32().ok_or_else(bad)?;
    let seg_inputs = |s: usize| -> Vec<usize> { xs.iter().filter(|&&x| x / per_in == s).map(|&x| x % per_in).collect() };
    let new_per_in = seg_inputs(0).len();
    let mut out = Vec::with_capacity(ys.len() * new_per_in * taps);
    for (r, &y) in ys.iter().enumerate() {
        let cols = seg_inputs(y / per_out);
        if cols.len() != new_per_in {
            return Err(anyhow!("grouped conv segments are unbalanced after pruning"));
        }
        for c in cols {
            let at = (r * per_in + c) * taps;
            out.extend_from_slice(&src[at..at + taps]);
        }
    }
    let mut shape = w.shape.clone();
    shape[0] = ys.len();
    shape[1] = new_per_in;
    Ok((Tensor::f32(shape, out), group))
}

/// A Split's output sizes on its `channels`-wide input, however the model spells them.
fn split_sizes(g: &GraphProto, n: &crate::onnx::proto::NodeProto, channels: usize) -> Result<Vec<usize>> {
    if let Some(s) = n.input.get(1).filter(|s| !s.is_empty()) {
        return Ok(constant(g, s)?.as_i64s().ok_or_else(|| anyhow!("split sizes of {} are not integers", n.name))?.iter().map(|&v| v.max(0) as usize).collect());
    }
    if let Some(v) = attr::ints(n, "split") {
        return Ok(v.iter().map(|&v| v.max(0) as usize).collect());
    }
    let parts = n.output.len().max(1);
    let each = channels.div_ceil(parts);
    Ok((0..parts).map(|j| each.min(channels.saturating_sub(j * each))).collect())
}

/// Writes explicit split sizes: an input from opset 13 on, an attribute before.
fn set_split(g: &mut GraphProto, i: usize, sizes: Vec<i64>, opset: i64) -> Result<()> {
    g.node[i].attribute.retain(|a| a.name != "num_outputs" && a.name != "split");
    if opset >= 13 {
        let t = Tensor::new(vec![sizes.len()], TensorData::I64(sizes));
        if g.node[i].input.len() < 2 {
            g.node[i].input.push(String::new());
        }
        let name = fresh_name(g, &format!("{}_split_pruned", g.node[i].name));
        set_initializer(g, from_tensor(&name, &t));
        g.node[i].input[1] = name;
    } else {
        g.node[i].attribute.push(AttributeProto { name: "split".into(), r#type: 7, ints: sizes, ..Default::default() });
    }
    Ok(())
}

/// A channel-axis Slice re-expressed over the kept input positions `xs` (of `channels`).
fn rewrite_slice(g: &mut GraphProto, i: usize, xs: &[usize], channels: usize) -> Result<usize> {
    let n = g.node[i].clone();
    let read = |k: usize| -> Result<Option<Vec<i64>>> {
        match n.input.get(k).filter(|s| !s.is_empty()) {
            Some(s) => Ok(Some(constant(g, s)?.as_i64s().ok_or_else(|| anyhow!("Slice {} has non-integer bounds", n.name))?)),
            None => Ok(None),
        }
    };
    let (mut starts, mut ends) = (read(1)?.unwrap_or_default(), read(2)?.unwrap_or_default());
    let axes = read(3)?.unwrap_or_else(|| (0..starts.len() as i64).collect());
    let Some(k) = axes.iter().position(|&a| a == 1 || a == -3) else { return Ok(0) };
    let c = channels as i64;
    let norm = |v: i64| if v < 0 { v + c } else { v }.clamp(0, c) as usize;
    let count_below = |p: usize| xs.iter().filter(|&&x| x < p).count() as i64;
    starts[k] = count_below(norm(starts[k]));
    ends[k] = count_below(norm(ends[k]));
    set_input_constant(g, i, 1, &Tensor::new(vec![starts.len()], TensorData::I64(starts)), "pruned");
    set_input_constant(g, i, 2, &Tensor::new(vec![ends.len()], TensorData::I64(ends)), "pruned");
    Ok(2)
}
