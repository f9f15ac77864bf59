//! A depthwise convolution wider than tract's SIMD kernel split into bands of its kernel,
//! summed (the `split-wide-depthwise` pass; the tract runtime applies it to what it loads).
//! Every product of the original appears in exactly one band: the result is the original's
//! up to the order of its float sums.

use crate::onnx::attr;
use crate::onnx::edit::{add_constant, fresh_name, initializer};
use crate::onnx::proto::{GraphProto, NodeProto};
use crate::onnx::tensor_proto::to_tensor;
use crate::tensor::Tensor;
use anyhow::Result;

/// The most taps tract-core 0.23's depthwise SIMD kernel takes (`MAX_VECTORISED_TAPS` in its
/// `depth_wise.rs`); wider zones fall back to a scalar loop, about ten times slower.
pub const MAX_TAPS: usize = 128;

/// Splits every wide depthwise convolution of `g`; returns what was split and what was left.
pub fn split_all(g: &mut GraphProto) -> Result<(Vec<serde_json::Value>, Vec<serde_json::Value>)> {
    let (mut split, mut left) = (Vec::new(), Vec::new());
    let mut i = 0;
    while i < g.node.len() {
        let n = &g.node[i];
        let plan = match wide_depthwise(g, n) {
            None => {
                i += 1;
                continue;
            }
            Some(p) => p,
        };
        let name = n.name.clone();
        match plan {
            Err(reason) => {
                left.push(serde_json::json!({ "node": name, "reason": reason }));
                i += 1;
            }
            Ok((weights, geometry, bands)) => {
                let nodes = band_nodes(g, i, &weights, &geometry, &bands);
                let added = nodes.len();
                split.push(serde_json::json!({
                    "node": name,
                    "kernel": [geometry.kernel[0], geometry.kernel[1]],
                    "bands": bands.iter().map(|b| [b[0].len(), b[1].len()]).collect::<Vec<_>>(),
                }));
                g.node.splice(i..=i, nodes);
                i += added;
            }
        }
    }
    if !split.is_empty() {
        super::dce::eliminate(g)?;
    }
    Ok((split, left))
}

/// Whether `g` has a depthwise convolution this pass would split.
pub fn any_to_split(g: &GraphProto) -> bool {
    g.node.iter().any(|n| matches!(wide_depthwise(g, n), Some(Ok(_))))
}

/// A convolution's kernel size, padding (begin, end), stride and dilation per spatial axis.
struct Geometry {
    kernel: [usize; 2],
    pads: [[usize; 2]; 2],
    strides: [i64; 2],
    dilations: [usize; 2],
}

/// One axis of a band: the kernel positions it spans (`extent`) and those it computes
/// (`own`, a sub-range); the rest of its extent are zero taps.
#[derive(Clone, Debug, PartialEq)]
struct Span {
    extent: std::ops::Range<usize>,
    own: std::ops::Range<usize>,
}

impl Span {
    fn len(&self) -> usize {
        self.extent.len()
    }
}

type Plan = (Tensor, Geometry, Vec<[Span; 2]>);

/// None when `n` is not a depthwise convolution wider than [`MAX_TAPS`]; otherwise its
/// weights, geometry and bands, or why it stays whole.
fn wide_depthwise(g: &GraphProto, n: &NodeProto) -> Option<Result<Plan, String>> {
    if n.op_type != "Conv" {
        return None;
    }
    let w = initializer(g, n.input.get(1)?)?;
    let dims: Vec<usize> = w.dims.iter().map(|&d| d.max(0) as usize).collect();
    let group = attr::int(n, "group", 1);
    if dims.len() != 4 || dims[1] != 1 || group <= 1 || group as usize != dims[0] || dims[2] * dims[3] <= MAX_TAPS {
        return None;
    }
    Some(plan(n, w, &dims))
}

fn plan(n: &NodeProto, w: &crate::onnx::proto::TensorProto, dims: &[usize]) -> Result<Plan, String> {
    if !matches!(attr::string(n, "auto_pad", "NOTSET").as_str(), "NOTSET" | "") {
        return Err("auto_pad instead of explicit pads".into());
    }
    let weights = to_tensor(w).map_err(|e| e.to_string())?;
    if weights.as_f32().is_none() {
        return Err(format!("weights are {:?}, not f32", weights.dtype()));
    }
    let pads = attr::ints(n, "pads").unwrap_or(vec![0; 4]);
    let strides = attr::ints(n, "strides").unwrap_or(vec![1, 1]);
    let dilations = attr::ints(n, "dilations").unwrap_or(vec![1, 1]);
    if pads.len() != 4 || strides.len() != 2 || dilations.len() != 2 || pads.iter().chain(&dilations).any(|&v| v < 0) || dilations.contains(&0) {
        return Err(format!("pads {pads:?}, strides {strides:?}, dilations {dilations:?} are not a 2-D convolution's"));
    }
    let geometry = Geometry {
        kernel: [dims[2], dims[3]],
        pads: [[pads[0] as usize, pads[2] as usize], [pads[1] as usize, pads[3] as usize]],
        strides: [strides[0], strides[1]],
        dilations: [dilations[0] as usize, dilations[1] as usize],
    };
    let axis = |a: usize| (axis_spans(geometry.kernel[a], geometry.pads[a], geometry.dilations[a], 1), axis_spans(geometry.kernel[a], geometry.pads[a], geometry.dilations[a], 2));
    let (rows, cols) = (axis(0), axis(1));
    // Fewest bands first: rows only, columns only, then both.
    let candidates = [(Some(&rows.1), Some(&cols.0)), (Some(&rows.0), Some(&cols.1)), (Some(&rows.1), Some(&cols.1))];
    for (r, c) in candidates {
        let (Some(Some(r)), Some(Some(c))) = (r, c) else { continue };
        let bands: Vec<[Span; 2]> = r.iter().flat_map(|rs| c.iter().map(move |cs| [rs.clone(), cs.clone()])).collect();
        if bands.iter().all(|b| b[0].len() * b[1].len() <= MAX_TAPS) {
            return Ok((weights, geometry, bands));
        }
    }
    Err(format!("no split of its {}x{} kernel into bands of at most {MAX_TAPS} taps keeps the padding non-negative", dims[2], dims[3]))
}

/// The spans of one axis in `parts` (1 or 2) bands, or None when two bands would not be
/// narrower than the kernel. A band may start at most `pad_begin / dilation` positions into
/// the kernel and end at most `pad_end / dilation` before its end: its own padding is the
/// original's less what it skips, and must stay non-negative.
fn axis_spans(kernel: usize, [pad_begin, pad_end]: [usize; 2], dilation: usize, parts: usize) -> Option<Vec<Span>> {
    if parts == 1 {
        return Some(vec![Span { extent: 0..kernel, own: 0..kernel }]);
    }
    let latest_start = (pad_begin / dilation).min(kernel - 1);
    let earliest_end = kernel.saturating_sub(pad_end / dilation).max(1);
    let (widest, s) = (1..kernel).map(|s| (s.max(earliest_end).max(kernel - s.min(latest_start)), s)).min()?;
    if widest >= kernel {
        return None;
    }
    Some(vec![Span { extent: 0..s.max(earliest_end), own: 0..s }, Span { extent: s.min(latest_start)..kernel, own: s..kernel }])
}

/// The band convolutions replacing node `i` and the Adds summing them into its output.
fn band_nodes(g: &mut GraphProto, i: usize, weights: &Tensor, geo: &Geometry, bands: &[[Span; 2]]) -> Vec<NodeProto> {
    let old = g.node[i].clone();
    let base = if old.name.is_empty() { "depthwise".to_string() } else { old.name.clone() };
    let w = weights.as_f32().expect("checked by plan");
    let (c, [kh, kw]) = (weights.shape[0], geo.kernel);
    let mut nodes = Vec::new();
    let mut sum: Option<String> = None;
    for (b, [rows, cols]) in bands.iter().enumerate() {
        let (bh, bw) = (rows.len(), cols.len());
        let mut bw_data = vec![0f32; c * bh * bw];
        for ch in 0..c {
            for y in rows.own.clone() {
                for x in cols.own.clone() {
                    bw_data[(ch * bh + y - rows.extent.start) * bw + x - cols.extent.start] = w[(ch * kh + y) * kw + x];
                }
            }
        }
        let wname = add_constant(g, &format!("{base}_band{b}_w"), &Tensor::f32(vec![c, 1, bh, bw], bw_data));
        let mut input = vec![old.input[0].clone(), wname];
        if b == 0 {
            input.extend(old.input.get(2).filter(|s| !s.is_empty()).cloned());
        }
        let pads = [
            geo.pads[0][0] - rows.extent.start * geo.dilations[0],
            geo.pads[1][0] - cols.extent.start * geo.dilations[1],
            geo.pads[0][1] - (kh - rows.extent.end) * geo.dilations[0],
            geo.pads[1][1] - (kw - cols.extent.end) * geo.dilations[1],
        ];
        // Names from distinct bases cannot meet, so they need not be in the graph yet.
        let out = fresh_name(g, &format!("{base}_band{b}"));
        nodes.push(NodeProto {
            name: format!("{base}_band{b}"),
            op_type: "Conv".into(),
            input,
            output: vec![out.clone()],
            attribute: vec![
                attr::make_int("group", c as i64),
                attr::make_ints("kernel_shape", vec![bh as i64, bw as i64]),
                attr::make_ints("pads", pads.iter().map(|&p| p as i64).collect()),
                attr::make_ints("strides", geo.strides.to_vec()),
                attr::make_ints("dilations", geo.dilations.iter().map(|&d| d as i64).collect()),
            ],
            ..Default::default()
        });
        sum = Some(match sum {
            None => out,
            Some(acc) => {
                let last = b + 1 == bands.len();
                let to = if last { old.output[0].clone() } else { fresh_name(g, &format!("{base}_sum{b}")) };
                nodes.push(NodeProto { name: format!("{base}_sum{b}"), op_type: "Add".into(), input: vec![acc, out], output: vec![to.clone()], ..Default::default() });
                to
            }
        });
    }
    nodes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_padding_splits_at_the_anchor() {
        // 15 taps, pad 7: bands [0, 8) and [7, 15), the shared row computed once.
        let spans = axis_spans(15, [7, 7], 1, 2).unwrap();
        assert_eq!(spans, vec![Span { extent: 0..8, own: 0..7 }, Span { extent: 7..15, own: 7..15 }]);
        // Without padding no band can skip a row.
        assert_eq!(axis_spans(15, [0, 0], 1, 2), None);
        // Dilation 2 with pad 14 reaches the same anchor.
        assert_eq!(axis_spans(15, [14, 14], 2, 2).unwrap()[1].extent, 7..15);
    }
}
