//! Cutting a detector's geometry: a window of the input frame, and a subset of its detection
//! levels (strides), with every position-dependent constant following the cut.
//!
//! What moves with the frame: constant maps with a pair of axes laid out like a feature map
//! at stride s (H/s × W/s: the folded PSF gate maps, YOLOv5's decode grids), constants along
//! the decode's flattened candidate axis (YOLOv8's anchor points and stride column), the
//! Concats that gather the levels' candidates, Reshape targets and Resize sizes. A constant
//! map is *cropped*, never recomputed, so the gate at frame pixel (x, y) stays the gate of
//! (x, y) and a grid cell keeps its frame coordinates: boxes come out where they are in the
//! full frame.

use crate::analysis::channels::detector_convolutions;
use crate::ir::{infer, Graph, Inferred};
use crate::onnx::edit::{initializer, set_initializer};
use crate::onnx::proto::{DimensionValue, GraphProto, TensorShapeProto, TypeValue, ValueInfoProto};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Result};
use serde::Serialize;
use std::collections::HashSet;

use super::Roi;

/// A detection level: the stride and the cells of its head convolution's output.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Level {
    pub stride: usize,
    pub height: usize,
    pub width: usize,
}

/// The image input, its (height, width), and the head's levels, finest first.
pub fn levels(g: &GraphProto) -> Result<(String, [usize; 2], Vec<Level>)> {
    let (input, [_, _, h, w]) = crate::ir::shapes::static_image_input(g, "scene specialization")?;
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let mut out: Vec<Level> = Vec::new();
    for node in detector_convolutions(&graph) {
        let o = &graph.node(node).output[0];
        let Some([1, _, lh, lw]) = inf.shape(o).and_then(|s| <[usize; 4]>::try_from(s).ok()) else {
            bail!("head convolution '{}' has no static [1, C, H, W] output", graph.node(node).name);
        };
        if lh == 0 || h % lh != 0 || h / lh != w / lw.max(1) || w % lw != 0 {
            bail!("head convolution '{}' outputs {lh}×{lw}, not the input {h}×{w} over an integer stride", graph.node(node).name);
        }
        let l = Level { stride: h / lh, height: lh, width: lw };
        if !out.contains(&l) {
            out.push(l);
        }
    }
    if out.is_empty() {
        bail!("no detection head found (no convolution feeds the decode)");
    }
    out.sort_by_key(|l| l.stride);
    Ok((input, [h, w], out))
}

/// What to keep: a window of the input (input pixels) and which levels.
pub struct Cut {
    pub window: Roi,
    pub keep: Vec<bool>,
}

#[derive(Serialize, Default)]
pub struct CutReport {
    /// Constants cropped or subset: (name, how).
    pub constants: Vec<(String, String)>,
    pub reshapes: usize,
    pub concats: usize,
}

/// Applies `cut` to `g`. The window must be aligned to the coarsest stride of the graph.
pub fn apply(g: &mut GraphProto, cut: &Cut) -> Result<CutReport> {
    let (input, [fh, fw], levels) = levels(g)?;
    if cut.keep.len() != levels.len() {
        bail!("internal: {} level flags for {} levels", cut.keep.len(), levels.len());
    }
    let old = infer(&Graph::build(g)?);
    let mut report = CutReport::default();
    let r = cut.window;
    if r.x + r.w > fw || r.y + r.h > fh {
        bail!("roi {}x{} at ({}, {}) does not fit in the {fw}x{fh} input", r.w, r.h, r.x, r.y);
    }
    let coarsest = coarsest_stride(&old, [fh, fw]);
    if [r.x, r.y, r.w, r.h].iter().any(|v| v % coarsest != 0) {
        bail!("roi x, y, w, h must be multiples of {coarsest} (the model's coarsest stride); got {r:?}");
    }

    // 1. The level Concats lose the dropped levels' inputs.
    for i in 0..g.node.len() {
        let n = &g.node[i];
        if n.op_type != "Concat" || n.input.len() != levels.len() {
            continue;
        }
        let axis = crate::onnx::attr::int(n, "axis", 0);
        let sizes: Option<Vec<usize>> = n.input.iter().map(|v| old.shape(v).and_then(|s| s.get(norm_axis(axis, s.len())?).copied())).collect();
        let Some(sizes) = sizes else { continue };
        let k = sizes[0] / (levels[0].height * levels[0].width).max(1);
        if k == 0 || sizes.iter().zip(&levels).any(|(&s, l)| s != k * l.height * l.width) {
            continue;
        }
        let kept: Vec<String> = g.node[i].input.iter().zip(&cut.keep).filter(|(_, &k)| k).map(|(v, _)| v.clone()).collect();
        if kept.len() != g.node[i].input.len() {
            g.node[i].input = kept;
            report.concats += 1;
        }
    }
    crate::ir::rewrite::dce::eliminate(g)?;

    // 2. The input becomes the window.
    set_dims(g, &input, &[1, -1, r.h as i64, r.w as i64]);

    // 3. Position-dependent constants.
    let graph_consumers: Vec<(String, String)> = g
        .node
        .iter()
        .filter(|n| ELEMENTWISE.contains(&n.op_type.as_str()))
        .flat_map(|n| n.input.iter().map(move |i| (i.clone(), n.output[0].clone())))
        .collect();
    let mut done = HashSet::new();
    for (name, out) in graph_consumers {
        if done.contains(&name) {
            continue;
        }
        let (Some(t), Some(os)) = (initializer(g, &name), old.shape(&out)) else { continue };
        let t = to_tensor(t)?;
        if let Some((cropped, how)) = crop_constant(&t, &os, [fh, fw], &levels, cut)? {
            // Same name: every reader of a positional constant is cut the same way, and a
            // cropped map stays recognizable next to the full model's.
            set_initializer(g, from_tensor(&name, &cropped));
            report.constants.push((name.clone(), how));
            done.insert(name);
        }
    }

    report.reshapes = follow_shapes(g, &old)?;
    Ok(report)
}

const ELEMENTWISE: &[&str] = &["Add", "Sub", "Mul", "Div", "Pow", "Where", "Max", "Min"];

fn norm_axis(axis: i64, rank: usize) -> Option<usize> {
    let a = if axis < 0 { axis + rank as i64 } else { axis };
    (0..rank as i64).contains(&a).then_some(a as usize)
}

/// The largest input-to-feature-map ratio anywhere in the graph.
fn coarsest_stride(inf: &Inferred, [h, w]: [usize; 2]) -> usize {
    inf.types
        .values()
        .filter_map(|t| t.static_shape())
        .filter(|s| s.len() == 4 && s[2] > 0 && s[3] > 0 && h % s[2] == 0 && w % s[3] == 0 && h / s[2] == w / s[3])
        .map(|s| h / s[2])
        .max()
        .unwrap_or(1)
}

/// Old positions of the kept candidates on a flattened candidate axis: the levels'
/// blocks one after the other, each in (k, y, x) order with k candidates per cell.
pub fn candidate_index(levels: &[Level], keep: &[bool], window: Roi, k: usize) -> Vec<usize> {
    let mut out = Vec::new();
    let mut offset = 0;
    for (l, &keep) in levels.iter().zip(keep) {
        let cells = l.height * l.width;
        if keep {
            let (y0, x0) = (window.y / l.stride, window.x / l.stride);
            for j in 0..k {
                for y in y0..y0 + window.h / l.stride {
                    out.extend((x0..x0 + window.w / l.stride).map(|x| offset + j * cells + y * l.width + x));
                }
            }
        }
        offset += k * cells;
    }
    out
}

/// The constant cut to the window, or `None` when it does not depend on position.
fn crop_constant(t: &Tensor, out: &[usize], [fh, fw]: [usize; 2], levels: &[Level], cut: &Cut) -> Result<Option<(Tensor, String)>> {
    let r = cut.window;
    let rank = t.shape.len();
    if rank == 0 || rank > out.len() {
        return Ok(None);
    }
    // Align the constant's axes with the output's (numpy broadcasting).
    let shift = out.len() - rank;
    for a in (0..rank.saturating_sub(1)).rev() {
        let (dh, dw) = (t.shape[a], t.shape[a + 1]);
        if dh < 2 || dw < 2 || out[a + shift] != dh || out[a + shift + 1] != dw || fh % dh != 0 || fw % dw != 0 || fh / dh != fw / dw {
            continue;
        }
        let s = fh / dh;
        let rows: Vec<usize> = (r.y / s..(r.y + r.h) / s).collect();
        let cols: Vec<usize> = (r.x / s..(r.x + r.w) / s).collect();
        let c = t.select(a, &rows).and_then(|c| c.select(a + 1, &cols)).ok_or_else(|| anyhow!("cannot crop a constant of shape {:?}", t.shape))?;
        return Ok(Some((c, format!("cropped axes {a},{} at stride {s}", a + 1))));
    }
    let total: usize = levels.iter().map(|l| l.height * l.width).sum();
    for a in 0..rank {
        let d = t.shape[a];
        if d < 2 || out[a + shift] != d || !d.is_multiple_of(total) {
            continue;
        }
        let idx = candidate_index(levels, &cut.keep, cut.window, d / total);
        let c = t.select(a, &idx).ok_or_else(|| anyhow!("cannot select candidates of a constant of shape {:?}", t.shape))?;
        return Ok(Some((c, format!("candidates on axis {a}: {d} -> {}", idx.len()))));
    }
    Ok(None)
}

/// After an edit that changed value shapes (`old`: the inference before it): Reshape
/// targets and Resize sizes follow their inputs, declared shapes are inferred again.
/// Returns how many targets changed.
pub fn follow_shapes(g: &mut GraphProto, old: &Inferred) -> Result<usize> {
    let n = retarget_shapes(g, old)?;
    // The old targets are read by nobody now.
    crate::ir::rewrite::dce::eliminate(g)?;
    refresh_declared_shapes(g)?;
    Ok(n)
}

/// Rewrites every constant Reshape target (and Resize `sizes`) whose input changed shape,
/// in node order, each against the shapes the edits before it produced; returns how many.
fn retarget_shapes(g: &mut GraphProto, old: &Inferred) -> Result<usize> {
    let mut changed = 0;
    // Shapes downstream of a rewritten target change: infer again only after a rewrite.
    let mut new = infer(&Graph::build(g)?);
    for i in 0..g.node.len() {
        let op = g.node[i].op_type.clone();
        if op != "Reshape" && op != "Resize" {
            continue;
        }
        let n = &g.node[i];
        let (Some(old_in), Some(new_in)) = (old.shape(&n.input[0]), new.shape(&n.input[0])) else {
            bail!("node '{}' ({op}) has no static input shape", n.name);
        };
        if old_in == new_in {
            continue;
        }
        let slot = if op == "Reshape" { 1 } else { 3 };
        let Some(target_name) = n.input.get(slot).filter(|s| !s.is_empty()).cloned() else { continue };
        let Some(old_out) = old.shape(&n.output[0]) else { bail!("node '{}' has no static output shape", n.name) };
        if initializer(g, &target_name).is_none() {
            bail!("node '{}' ({op}) computes its target shape at run time; run fold-constants before specializing", n.name);
        };
        let new_target: Vec<i64> = if op == "Reshape" {
            reshape_target(&old_in, &old_out, &new_in).ok_or_else(|| anyhow!("cannot retarget Reshape '{}' from {old_in:?} -> {old_out:?} for input {new_in:?}", n.name))?
        } else {
            old_out.iter().zip(old_in.iter().zip(&new_in)).map(|(&o, (&a, &b))| (o * b / a.max(1)) as i64).collect()
        };
        let tensor = Tensor::new(vec![new_target.len()], TensorData::I64(new_target));
        crate::onnx::edit::set_input_constant(g, i, slot, &tensor, "scene");
        changed += 1;
        new = infer(&Graph::build(g)?);
    }
    Ok(changed)
}

/// A Reshape's new target for a new input shape: the dims are grouped where the old input
/// and output products agree; a group whose input changed takes the new product, on its
/// only output dim or on the one output dim that divides it evenly.
pub fn reshape_target(old_in: &[usize], old_out: &[usize], new_in: &[usize]) -> Option<Vec<i64>> {
    if old_in.len() != new_in.len() {
        return None;
    }
    let mut out: Vec<i64> = old_out.iter().map(|&d| d as i64).collect();
    let (mut i, mut j) = (0, 0);
    while i < old_in.len() || j < old_out.len() {
        let (i0, j0) = (i, j);
        let (mut pi, mut pj) = (*old_in.get(i)? as u64, *old_out.get(j)? as u64);
        i += 1;
        j += 1;
        while pi != pj {
            if pi < pj {
                pi *= *old_in.get(i)? as u64;
                i += 1;
            } else {
                pj *= *old_out.get(j)? as u64;
                j += 1;
            }
        }
        if old_in[i0..i] == new_in[i0..i] {
            continue;
        }
        let np: u64 = new_in[i0..i].iter().map(|&d| d as u64).product();
        if j - j0 == 1 {
            out[j0] = np as i64;
        } else if i - i0 == j - j0 && (i0..i).zip(j0..j).all(|(a, b)| old_in[a] == old_out[b]) {
            for (a, b) in (i0..i).zip(j0..j) {
                out[b] = new_in[a] as i64;
            }
        } else {
            let fits: Vec<usize> = (j0..j).filter(|&b| {
                let rest = pj / old_out[b] as u64;
                rest > 0 && np.is_multiple_of(rest) && np / rest != old_out[b] as u64
            }).collect();
            let [b] = fits[..] else { return None };
            out[b] = (np / (pj / old_out[b] as u64)) as i64;
        }
    }
    Some(out)
}

/// The declared shape of a value, where it has one.
fn shape_mut(v: &mut ValueInfoProto) -> Option<&mut TensorShapeProto> {
    match v.r#type.as_mut()?.value.as_mut()? {
        TypeValue::TensorType(t) => t.shape.as_mut(),
        _ => None,
    }
}

/// Sets the input's declared dims where `dims` gives one (≥ 0).
fn set_dims(g: &mut GraphProto, name: &str, dims: &[i64]) {
    for s in g.input.iter_mut().filter(|v| v.name == name).filter_map(shape_mut) {
        for (d, &n) in s.dim.iter_mut().zip(dims).filter(|(_, &n)| n >= 0) {
            d.value = Some(DimensionValue::DimValue(n));
        }
    }
}

/// Declared shapes of outputs and intermediate values, from inference on the cut graph.
fn refresh_declared_shapes(g: &mut GraphProto) -> Result<()> {
    g.value_info.clear();
    let inf = infer(&Graph::build(g)?);
    let outs: Vec<(String, Vec<usize>)> = g.output.iter().map(|o| Ok((o.name.clone(), inf.shape(&o.name).ok_or_else(|| anyhow!("output '{}' lost its static shape", o.name))?))).collect::<Result<_>>()?;
    for (name, shape) in outs {
        for s in g.output.iter_mut().filter(|v| v.name == name).filter_map(shape_mut) {
            s.dim = shape.iter().map(|&d| crate::onnx::proto::Dimension { value: Some(DimensionValue::DimValue(d as i64)), ..Default::default() }).collect();
        }
    }
    crate::ir::rewrite::value_info::write_value_info(g)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::reshape_target;

    #[test]
    fn reshape_targets_follow_the_input() {
        // YOLOv5 head: classes dropped (33 = 3 anchors × 11 -> 3 × 7), rows cropped.
        assert_eq!(reshape_target(&[1, 33, 24, 32], &[1, 3, 11, 24, 32], &[1, 21, 24, 32]), Some(vec![1, 3, 7, 24, 32]));
        assert_eq!(reshape_target(&[1, 33, 24, 32], &[1, 3, 11, 24, 32], &[1, 33, 16, 32]), Some(vec![1, 3, 11, 16, 32]));
        assert_eq!(reshape_target(&[1, 3, 24, 32, 11], &[1, 2304, 11], &[1, 3, 16, 32, 7]), Some(vec![1, 1536, 7]));
        // YOLOv8 DFL: [1, 64, N] -> [1, 4, 16, N] with fewer candidates.
        assert_eq!(reshape_target(&[1, 64, 1008], &[1, 4, 16, 1008], &[1, 64, 960]), Some(vec![1, 4, 16, 960]));
        assert_eq!(reshape_target(&[1, 1, 4, 1008], &[1, 4, 1008], &[1, 1, 4, 672]), Some(vec![1, 4, 672]));
        assert_eq!(reshape_target(&[1, 70, 24, 32], &[1, 70, 768], &[1, 70, 16, 32]), Some(vec![1, 70, 512]));
        // 12 -> 2 × 6 with 8: neither 2 nor 6 can take it alone.
        assert_eq!(reshape_target(&[12], &[2, 6], &[8]), Some(vec![2, 4]));
        assert_eq!(reshape_target(&[12], &[2, 6], &[7]), None);
    }
}
