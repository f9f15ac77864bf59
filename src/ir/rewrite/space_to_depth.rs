//! A narrow block at full resolution run on 2x2 pixel blocks (the `space-to-depth` pass):
//! SpaceToDepth, then each convolution on four times the channels at half the height and
//! width, and the 2x2 max pooling that ends the block as the maximum of the four pixel
//! positions (Split, Max).
//!
//! A stride-1 convolution with kernel 2p+1 and padding p reads, for the pixel at position a of
//! its 2-pixel block, the pixels a-p..a+p: blocks floor((a-p)/2)..floor((a+p)/2), so a kernel
//! of 2*ceil(p/2)+1 blocks with padding ceil(p/2). Each weight of the original lands once in
//! the block kernel and every other is zero: the same products summed in another order, at
//! four times the multiplications (3x3) of a layer four times as wide. Element-wise
//! activations act on each channel as before.
//!
//! Channel c of pixel position (a, b) is channel (2a + b) * C + c, as ONNX's SpaceToDepth
//! writes it; the convolutions keep that order, so a Split into four equal parts gives the
//! four positions of every block and their Max is the pooling's output.

use crate::ir::{infer, Graph};
use crate::onnx::attr;
use crate::onnx::edit::{add_constant, fresh_name, initializer, only_reader, swap_initializer};
use crate::onnx::proto::{AttributeProto, GraphProto, NodeProto, TypeValue};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::tensor::{DType, Tensor, TensorData};
use anyhow::{anyhow, Result};
use std::collections::HashSet;

/// Element-wise activations a block may hold between its convolutions.
const ELEMENTWISE: &[&str] = &["Relu", "LeakyRelu", "Clip", "Sigmoid", "Tanh", "HardSigmoid", "HardSwish"];

/// A block to rewrite: its nodes from the first convolution up to the pooling, in order, and
/// the pooling.
#[derive(Debug, Clone)]
pub struct Block {
    pub nodes: Vec<usize>,
    pub pool: usize,
    /// Input and output channels of each convolution, in order.
    pub channels: Vec<(usize, usize)>,
    /// The block's input shape (N, C, H, W).
    pub input: Vec<usize>,
}

/// The blocks of `g` to rewrite: a chain of stride-1 group-1 convolutions (f32 weights in
/// initializers, odd kernels padded to keep the size, at most `max_channels` in and out) and
/// element-wise activations, each value read by the next node alone, ending in a 2x2 max
/// pooling of stride 2, on an input whose height and width are even.
pub fn blocks(g: &GraphProto, max_channels: usize) -> Result<Vec<Block>> {
    let graph = Graph::build(g)?;
    let shapes = infer(&graph);
    let outputs: HashSet<&str> = g.output.iter().map(|o| o.name.as_str()).collect();
    let only_reader = |v: &str| match graph.consumers_of(v) {
        [r] if !outputs.contains(v) => Some(*r),
        _ => None,
    };
    let mut out = Vec::new();
    for (p, pool) in g.node.iter().enumerate() {
        if !halving_pool(pool) {
            continue;
        }
        // Back from the pooling while each node is one the block may hold: (node, its
        // channels in and out if it is a convolution).
        let mut held: Vec<(usize, Option<(usize, usize)>)> = vec![];
        let mut v = pool.input[0].as_str();
        while let Some(&i) = graph.producer.get(v) {
            let n = &g.node[i];
            let conv = if n.op_type == "Conv" { same_size_conv(g, n, max_channels) } else { None };
            let fits = conv.is_some()
                || (ELEMENTWISE.contains(&n.op_type.as_str()) && n.input.iter().skip(1).all(|c| c.is_empty() || initializer(g, c).is_some_and(|t| t.dims.iter().product::<i64>() == 1)));
            if !fits || only_reader(v) != Some(held.last().map_or(p, |&(j, _)| j)) {
                break;
            }
            held.push((i, conv));
            v = n.input[0].as_str();
        }
        // The block starts at its first convolution.
        while held.last().is_some_and(|&(_, conv)| conv.is_none()) {
            held.pop();
        }
        if held.is_empty() {
            continue;
        }
        held.reverse();
        let (nodes, convs): (Vec<usize>, Vec<Option<(usize, usize)>>) = held.into_iter().unzip();
        let x = &g.node[nodes[0]].input[0];
        let Some(input) = shapes.types.get(x.as_str()).and_then(|t| t.static_shape()) else { continue };
        if input.len() != 4 || input[2] % 2 != 0 || input[3] % 2 != 0 || input[2] == 0 || input[3] == 0 {
            continue;
        }
        out.push(Block { nodes, pool: p, channels: convs.into_iter().flatten().collect(), input });
    }
    Ok(out)
}

/// A MaxPool of kernel 2x2, stride 2, no padding or dilation, without indices.
fn halving_pool(n: &NodeProto) -> bool {
    let is = |name: &str, v: &[i64]| attr::ints(n, name).is_none_or(|x| x == v);
    n.op_type == "MaxPool"
        && n.output.len() == 1
        && attr::ints(n, "kernel_shape").as_deref() == Some(&[2, 2])
        && attr::ints(n, "strides").as_deref() == Some(&[2, 2])
        && is("pads", &[0, 0, 0, 0])
        && is("dilations", &[1, 1])
        && attr::int(n, "ceil_mode", 0) == 0
        && attr::int(n, "storage_order", 0) == 0
        && attr::string(n, "auto_pad", "NOTSET") == "NOTSET"
}

/// (input, output channels) of a convolution the block may hold: group 1, stride 1, no
/// dilation, an odd kernel padded by half of it on every side, f32 weights (and bias) in
/// initializers, at most `max_channels` in and out.
fn same_size_conv(g: &GraphProto, n: &NodeProto, max_channels: usize) -> Option<(usize, usize)> {
    let w = initializer(g, n.input.get(1)?)?;
    if w.dims.len() != 4 || w.data_type != DType::F32.onnx_code() || attr::int(n, "group", 1) != 1 {
        return None;
    }
    if let Some(b) = n.input.get(2).filter(|b| !b.is_empty()) {
        initializer(g, b).filter(|t| t.data_type == DType::F32.onnx_code())?;
    }
    let (kh, kw) = (w.dims[2], w.dims[3]);
    let ones = |name: &str| attr::ints(n, name).is_none_or(|v| v.iter().all(|&x| x == 1));
    let pads = attr::ints(n, "pads").unwrap_or(vec![0; 4]);
    let plain = kh % 2 == 1 && kw % 2 == 1 && ones("strides") && ones("dilations") && pads == [kh / 2, kw / 2, kh / 2, kw / 2]
        && attr::string(n, "auto_pad", "NOTSET") == "NOTSET"
        && attr::ints(n, "kernel_shape").is_none_or(|k| k == [kh, kw]);
    let (cout, cin) = (w.dims[0] as usize, w.dims[1] as usize);
    (plain && cin <= max_channels && cout <= max_channels).then_some((cin, cout))
}

/// Rewrites `block` of `g` on 2x2 blocks (nodes keep their names and output values, which
/// change shape). `opset` is the model's default opset (Split takes its sizes as an input
/// from 13, as an attribute before).
pub fn rewrite(g: &mut GraphProto, block: &Block, opset: i64) -> Result<()> {
    let first = g.node[block.nodes[0]].clone();
    let x = first.input[0].clone();
    let s2d_out = fresh_name(g, &format!("{x}_blocks"));
    for &i in &block.nodes {
        let n = g.node[i].clone();
        if n.op_type == "Conv" {
            let w = to_tensor(initializer(g, &n.input[1]).ok_or_else(|| anyhow!("'{}': weights are not an initializer", n.name))?)?;
            let weights = to_blocks(&w)?;
            let kb = weights.shape[2] as i64;
            let kbw = weights.shape[3] as i64;
            let wname = swap_initializer(g, &n.input[1], &format!("{}_blocks", n.input[1]), from_tensor("", &weights));
            let conv = &mut g.node[i];
            conv.input[1] = wname;
            set_ints(conv, "kernel_shape", vec![kb, kbw]);
            set_ints(conv, "pads", vec![kb / 2, kbw / 2, kb / 2, kbw / 2]);
            if let Some(b) = n.input.get(2).filter(|b| !b.is_empty()) {
                let bias = to_tensor(initializer(g, b).expect("checked by blocks"))?;
                let tiled = Tensor::f32(vec![bias.len() * 4], bias.as_f32().ok_or_else(|| anyhow!("bias of '{}' is not f32", n.name))?.repeat(4));
                g.node[i].input[2] = swap_initializer(g, b, &format!("{b}_blocks"), from_tensor("", &tiled));
            }
        }
        let y = g.node[i].output[0].clone();
        resize_info(g, &y, |d| vec![d[0], d[1] * 4, d[2] / 2, d[3] / 2]);
    }
    g.node[block.nodes[0]].input[0] = s2d_out.clone();
    let pool = g.node[block.pool].clone();
    let parts: Vec<String> = (0..4).map(|k| fresh_name(g, &format!("{}_position{k}", pool.output[0]))).collect();
    let mut split = NodeProto { name: format!("{}_positions", pool.name), op_type: "Split".into(), input: vec![pool.input[0].clone()], output: parts.clone(), attribute: vec![attr::make_int("axis", 1)], ..Default::default() };
    let c = block.channels.last().map_or(block.input[1], |&(_, cout)| cout) as i64;
    if opset >= 13 {
        split.input.push(add_constant(g, &format!("{}_positions_sizes", pool.name), &Tensor::new(vec![4], TensorData::I64(vec![c; 4]))));
    } else {
        split.attribute.push(attr::make_ints("split", vec![c; 4]));
    }
    let max = NodeProto { name: pool.name.clone(), op_type: "Max".into(), input: parts, output: pool.output.clone(), ..Default::default() };
    let s2d = NodeProto { name: format!("{}_space_to_depth", first.name), op_type: "SpaceToDepth".into(), input: vec![x], output: vec![s2d_out], attribute: vec![attr::make_int("blocksize", 2)], ..Default::default() };
    g.node.splice(block.pool..=block.pool, [split, max]);
    g.node.insert(block.nodes[0], s2d);
    Ok(())
}

/// `w` (O, I, 2p+1, 2q+1) as the weights of the same convolution on 2x2 blocks.
pub fn to_blocks(w: &Tensor) -> Result<Tensor> {
    let src = w.as_f32().ok_or_else(|| anyhow!("weights are not f32"))?;
    let [o, i, kh, kw] = w.shape[..] else { return Err(anyhow!("weights are not 4-D")) };
    let (ph, pw) = (kh / 2, kw / 2);
    let (qh, qw) = (ph.div_ceil(2), pw.div_ceil(2));
    let (bh, bw) = (2 * qh + 1, 2 * qw + 1);
    let mut out = vec![0f32; 16 * o * i * bh * bw];
    for a in 0..2 {
        for b in 0..2 {
            for dy in 0..kh {
                for dx in 0..kw {
                    // Input pixel a + dy - ph: its block row and position within the block.
                    let (ry, rx) = ((a + dy) as i64 - ph as i64, (b + dx) as i64 - pw as i64);
                    let (by, a2) = (ry.div_euclid(2), ry.rem_euclid(2) as usize);
                    let (bx, b2) = (rx.div_euclid(2), rx.rem_euclid(2) as usize);
                    let (ky, kx) = ((by + qh as i64) as usize, (bx + qw as i64) as usize);
                    for oc in 0..o {
                        for ic in 0..i {
                            let row = (2 * a + b) * o + oc;
                            let col = (2 * a2 + b2) * i + ic;
                            out[((row * 4 * i + col) * bh + ky) * bw + kx] = src[((oc * i + ic) * kh + dy) * kw + dx];
                        }
                    }
                }
            }
        }
    }
    Ok(Tensor::f32(vec![4 * o, 4 * i, bh, bw], out))
}

/// The weights on 2x2 blocks `wb` came from (the smallest kernel that gives them), if they are
/// such weights.
pub fn from_blocks(wb: &Tensor) -> Option<Tensor> {
    let src = wb.as_f32()?;
    let [o4, i4, bh, bw] = wb.shape[..] else { return None };
    if o4 % 4 != 0 || i4 % 4 != 0 || bh % 2 == 0 || bw % 2 == 0 {
        return None;
    }
    let (o, i) = (o4 / 4, i4 / 4);
    // A block kernel of 2q+1 comes from padding 2q-1 or 2q: the smaller first.
    let pads = |b: usize| if b == 1 { vec![0] } else { vec![b - 2, b - 1] };
    for ph in pads(bh) {
        for pw in pads(bw) {
            let (kh, kw) = (2 * ph + 1, 2 * pw + 1);
            // Position (0, 0) of each block reads every tap of the original.
            let mut w = vec![0f32; o * i * kh * kw];
            for dy in 0..kh {
                for dx in 0..kw {
                    let (ry, rx) = (dy as i64 - ph as i64, dx as i64 - pw as i64);
                    let (ky, kx) = ((ry.div_euclid(2) + (bh / 2) as i64) as usize, (rx.div_euclid(2) + (bw / 2) as i64) as usize);
                    let (a2, b2) = (ry.rem_euclid(2) as usize, rx.rem_euclid(2) as usize);
                    for oc in 0..o {
                        for ic in 0..i {
                            w[((oc * i + ic) * kh + dy) * kw + dx] = src[((oc * i4 + (2 * a2 + b2) * i + ic) * bh + ky) * bw + kx];
                        }
                    }
                }
            }
            let w = Tensor::f32(vec![o, i, kh, kw], w);
            let back = to_blocks(&w).ok()?;
            if back.shape == wb.shape && back.as_f32()?.iter().zip(src).all(|(a, b)| a.to_bits() == b.to_bits()) {
                return Some(w);
            }
        }
    }
    None
}

/// Undoes [`rewrite`] wherever `g` has its form, with f32 weights that are the block form of
/// a convolution: the block comes back under its own names. Returns how many were lowered.
pub fn lower_all(g: &mut GraphProto) -> Result<usize> {
    let mut count = 0;
    while let Some(found) = find_rewritten(g) {
        lower(g, &found)?;
        count += 1;
    }
    if count > 0 {
        super::dce::eliminate(g)?;
    }
    Ok(count)
}

/// Whether `g` has a block [`lower_all`] would lower.
pub fn any_rewritten(g: &GraphProto) -> bool {
    find_rewritten(g).is_some()
}

/// A rewritten block: (SpaceToDepth, nodes, their original convolution weights, Split, Max).
struct Found {
    s2d: usize,
    nodes: Vec<usize>,
    weights: Vec<Option<Tensor>>,
    split: usize,
    max: usize,
}

fn find_rewritten(g: &GraphProto) -> Option<Found> {
    let only_reader = |v: &str| only_reader(g, v);
    (0..g.node.len()).find_map(|s| {
        let sn = &g.node[s];
        if sn.op_type != "SpaceToDepth" || attr::int(sn, "blocksize", 0) != 2 {
            return None;
        }
        let (mut nodes, mut weights) = (vec![], vec![]);
        let mut v = sn.output[0].as_str();
        loop {
            let i = only_reader(v)?;
            let n = &g.node[i];
            if n.input[0] != v {
                return None;
            }
            match n.op_type.as_str() {
                "Conv" => {
                    let wb = to_tensor(initializer(g, n.input.get(1)?)?).ok()?;
                    let w = from_blocks(&wb)?;
                    let plain = attr::int(n, "group", 1) == 1 && attr::ints(n, "strides").is_none_or(|v| v.iter().all(|&x| x == 1)) && attr::ints(n, "dilations").is_none_or(|v| v.iter().all(|&x| x == 1));
                    if !plain || !tiled_bias(g, n) {
                        return None;
                    }
                    weights.push(Some(w));
                }
                op if ELEMENTWISE.contains(&op) => weights.push(None),
                "Split" => {
                    let parts = &n.output;
                    let m = only_reader(parts.first()?)?;
                    let mn = &g.node[m];
                    let four = parts.len() == 4 && attr::int(n, "axis", 0) == 1 && mn.op_type == "Max" && mn.input == *parts && parts.iter().all(|p| only_reader(p) == Some(m));
                    return (four && !nodes.is_empty()).then_some(Found { s2d: s, nodes, weights, split: i, max: m });
                }
                _ => return None,
            }
            nodes.push(i);
            v = g.node[i].output[0].as_str();
        }
    })
}

/// Whether the convolution's bias, if any, is an f32 initializer of four equal quarters.
fn tiled_bias(g: &GraphProto, n: &NodeProto) -> bool {
    let Some(b) = n.input.get(2).filter(|b| !b.is_empty()) else { return true };
    let Some(t) = initializer(g, b).and_then(|t| to_tensor(t).ok()) else { return false };
    let Some(v) = t.as_f32() else { return false };
    let q = v.len() / 4;
    v.len() % 4 == 0 && (1..4).all(|k| v[k * q..(k + 1) * q].iter().zip(&v[..q]).all(|(a, b)| a.to_bits() == b.to_bits()))
}

fn lower(g: &mut GraphProto, f: &Found) -> Result<()> {
    let x = g.node[f.s2d].input[0].clone();
    for (&i, w) in f.nodes.iter().zip(&f.weights) {
        if let Some(w) = w {
            let n = g.node[i].clone();
            let base = n.input[1].strip_suffix("_blocks").unwrap_or(&n.input[1]).to_string();
            let wname = swap_initializer(g, &n.input[1], &base, from_tensor("", w));
            let conv = &mut g.node[i];
            conv.input[1] = wname;
            set_ints(conv, "kernel_shape", vec![w.shape[2] as i64, w.shape[3] as i64]);
            let (ph, pw) = ((w.shape[2] / 2) as i64, (w.shape[3] / 2) as i64);
            set_ints(conv, "pads", vec![ph, pw, ph, pw]);
            if let Some(b) = n.input.get(2).filter(|b| !b.is_empty()) {
                let t = to_tensor(initializer(g, b).expect("checked by tiled_bias"))?;
                let v = t.as_f32().expect("checked by tiled_bias");
                let quarter = Tensor::f32(vec![v.len() / 4], v[..v.len() / 4].to_vec());
                let base = b.strip_suffix("_blocks").unwrap_or(b).to_string();
                g.node[i].input[2] = swap_initializer(g, b, &base, from_tensor("", &quarter));
            }
        }
        let y = g.node[i].output[0].clone();
        resize_info(g, &y, |d| vec![d[0], d[1] / 4, d[2] * 2, d[3] * 2]);
    }
    g.node[f.nodes[0]].input[0] = x;
    let last = g.node[*f.nodes.last().expect("a block has nodes")].output[0].clone();
    let max = &g.node[f.max];
    let pool = NodeProto {
        name: max.name.clone(),
        op_type: "MaxPool".into(),
        input: vec![last],
        output: max.output.clone(),
        attribute: vec![attr::make_ints("kernel_shape", vec![2, 2]), attr::make_ints("strides", vec![2, 2])],
        ..Default::default()
    };
    g.node[f.max] = pool;
    let dead: HashSet<usize> = [f.s2d, f.split].into();
    crate::onnx::edit::remove_nodes(g, &dead);
    Ok(())
}

/// Sets attribute `name` where it is (so that lowering gives back the same bytes), or adds it.
fn set_ints(n: &mut NodeProto, name: &str, v: Vec<i64>) {
    match n.attribute.iter_mut().find(|a: &&mut AttributeProto| a.name == name) {
        Some(a) => *a = attr::make_ints(name, v),
        None => n.attribute.push(attr::make_ints(name, v)),
    }
}

/// Applies `f` to the declared 4-D shape of `v`, if it has one.
fn resize_info(g: &mut GraphProto, v: &str, f: impl Fn(&[i64]) -> Vec<i64>) {
    use crate::onnx::proto::DimensionValue;
    for info in g.value_info.iter_mut().filter(|i| i.name == v) {
        let Some(TypeValue::TensorType(t)) = info.r#type.as_mut().and_then(|t| t.value.as_mut()) else { continue };
        let Some(shape) = t.shape.as_mut() else { continue };
        let dims: Option<Vec<i64>> = shape.dim.iter().map(|d| match d.value {
            Some(DimensionValue::DimValue(x)) => Some(x),
            _ => None,
        }).collect();
        match dims {
            Some(d) if d.len() == 4 => {
                for (slot, x) in shape.dim.iter_mut().zip(f(&d)) {
                    slot.value = Some(DimensionValue::DimValue(x));
                }
            }
            _ => shape.dim.clear(),
        }
    }
}
