//! `rknn-legalize`: end the detector where an NPU should end it.
//!
//! Needs: a float model with one fixed [1, C, H, W] image input, opset ≤ 19, whose outputs
//! include a recognized YOLOv5 (anchor) or YOLOv8 (DFL) in-graph decode.
//! Guarantees: the graph ends at the head convolutions; per stride S it outputs
//! `boxes_s{S}` and `scores_s{S}` (YOLOv8 also `score_sum_s{S}` = Clip(ReduceSum(scores), 0, 1)),
//! never a Concat of boxes with scores, so each output gets a quantization range of its own:
//! a pixel-coordinate box (0..640) sharing a tensor with probabilities (0..1) is what turns
//! every INT8 score into 0. YOLOv5's head convolution is split in two (box rows, score rows)
//! for the same reason; its boxes keep their Sigmoid (the decode only ever reads sigmoid(x),
//! and a [0, 1] range quantizes 4× finer than the logits). Every value has a static shape,
//! IR version ≤ 9. The head layout (strides, anchors read off the original decode, DFL bins)
//! is stored in the model's metadata for [`crate::detect::split_head`], and checked: the
//! original decode run by tract on random head logits equals the Rust decode of the split
//! tensors.
//! Reports: outputs, the head layout, the decode check, and what the NPU may not take as is
//! (large kernels, non-nearest Resize, Concat channel counts that are not multiples of 16).

use crate::analysis::channels::detector_convolutions;
use crate::analysis::head::{self, HeadKind};
use crate::detect::split_head::{decode_dense, HeadLayout, Level, METADATA_KEY};
use crate::ir::{infer, shapes::static_image_input, Graph};
use crate::onnx::attr;
use crate::onnx::edit::{fresh_name, tensor_value_info};
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::{AttributeProto, GraphProto, ModelProto, NodeProto, StringStringEntryProto};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use super::{Pass, PassContext};
use crate::runtime::{tract_runtime::TractRuntime, Runtime};
use crate::tensor::{DType, Tensor};
use anyhow::{anyhow, bail, Context, Result};
use std::collections::{BTreeMap, HashMap};

/// RKNN-Toolkit2 2.5 reads ONNX up to opset 19.
const MAX_OPSET: i64 = 19;
/// The RK3588 NPU's channel alignment: Concat/Split parts that are multiples of 16 need no
/// padding copies.
const CHANNEL_ALIGN: usize = 16;
/// Kernels up to this size are the NPU's common case; larger ones are reported (the 15×15
/// depthwise conv of the PALS-Bridge stays: rknn-convert shows it placed on the NPU).
const COMMON_KERNEL: i64 = 7;

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// Highest IR version written (RKNN-Toolkit2 2.5 reads ≤ 9).
    pub ir_version: i64,
    /// Emit YOLOv8's per-cell `score_sum` outputs.
    pub score_sum: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options { ir_version: 9, score_sum: true }
    }
}

pub struct RknnLegalize {
    pub options: Options,
}

/// A head convolution and where its output sits.
#[derive(Clone, Debug)]
struct HeadConv {
    node: usize,
    output: String,
    channels: usize,
    height: usize,
    width: usize,
}

impl Pass for RknnLegalize {
    fn name(&self) -> &'static str {
        "rknn-legalize"
    }

    fn provides(&self) -> Vec<super::Capability> {
        vec![super::Capability::SplitHead]
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        check_opset(model)?;
        let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let (_, [_, _, in_h, in_w]) = static_image_input(g, "rknn-legalize")?;
        let (kind, classes, reg_max, decoded, levels) = {
            let graph = Graph::build(g)?;
            let inf = infer(&graph);
            let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
            let h = head::detect(&graph, &inf, &outputs);
            if h.kind == HeadKind::Raw {
                bail!("rknn-legalize found no YOLOv5 or YOLOv8 decode behind the outputs ({}); it needs the original detection output", outputs.join(", "));
            }
            let classes = h.classes.ok_or_else(|| anyhow!("cannot tell the class count from the detection output's shape"))?;
            let decoded = h.output.clone().ok_or_else(|| anyhow!("the detection output has no static 3-D shape"))?;
            let mut levels: BTreeMap<usize, Vec<HeadConv>> = BTreeMap::new();
            for node in detector_convolutions(&graph) {
                let output = graph.node(node).output[0].clone();
                let Some([1, channels, height, width]) = inf.shape(&output).as_deref().map(|s| <[usize; 4]>::try_from(s).unwrap_or([0; 4])) else {
                    bail!("head convolution '{}' has no static [1, C, H, W] output shape", graph.node(node).name);
                };
                if height == 0 || width == 0 || in_h % height != 0 || in_h / height != in_w / width {
                    bail!("head convolution '{}' outputs {height}×{width}, not the input {in_h}×{in_w} over an integer stride", graph.node(node).name);
                }
                levels.entry(in_h / height).or_default().push(HeadConv { node, output, channels, height, width });
            }
            (h.kind, classes, h.reg_max, decoded, levels)
        };

        // One tract plan of the original decode serves the probe and the check.
        let zeros = zero_logits(&levels);
        let mut tail = TractRuntime::new(&decode_tail(model, &decoded, &levels)?, &zeros, 1).context("running the original decode on its own")?;
        let layout = probe_layout(&mut tail, &zeros, kind, classes, reg_max, &levels)?;
        let decode_check = check_decode(&mut tail, &layout, &levels)?;

        let opset = crate::onnx::edit::default_opset(model).unwrap_or(13);
        let g = super::graph_mut(model)?;
        let mut outputs = Vec::new();
        for (level, convs) in layout.levels.iter().zip(levels.values()) {
            split_level(g, opset, kind, classes, level, convs, self.options.score_sum, &mut outputs)?;
        }
        // The layout's order (boxes, scores, score_sum per stride), whatever the convs' order.
        let order = layout.output_names();
        outputs.sort_by_key(|o| order.iter().position(|n| *n == o.name));
        g.output = outputs;
        sort_topologically(g)?;
        let (nodes_removed, _, _) = crate::ir::rewrite::dce::eliminate(g)?;
        let unshaped = crate::ir::rewrite::value_info::write_value_info(g)?;
        if unshaped > 0 {
            bail!("{unshaped} values have no static shape after legalization; run fold-constants before rknn-legalize");
        }
        let notes = npu_notes(g)?;
        let ir_before = model.ir_version;
        model.ir_version = model.ir_version.min(self.options.ir_version);
        model.metadata_props.retain(|p| p.key != METADATA_KEY);
        model.metadata_props.push(StringStringEntryProto { key: METADATA_KEY.into(), value: serde_json::to_string(&layout)? });
        Ok(serde_json::json!({
            "outputs": layout.output_names(),
            "head_layout": layout,
            "decode_check_max_abs": decode_check,
            "nodes_removed": nodes_removed,
            "ir_version": { "before": ir_before, "after": model.ir_version },
            "npu_notes": notes,
        }))
    }
}

fn check_opset(model: &ModelProto) -> Result<()> {
    for o in &model.opset_import {
        match o.domain.as_str() {
            "" | "ai.onnx" if o.version > MAX_OPSET => {
                bail!("RKNN-Toolkit2 reads ONNX opset ≤ {MAX_OPSET}; this model is opset {}: re-export it with --opset 17", o.version)
            }
            _ => {}
        }
    }
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    if let Some(n) = g.node.iter().find(|n| !n.domain.is_empty() && n.domain != "ai.onnx") {
        bail!("node '{}' is a {}::{} op, which RKNN-Toolkit2 cannot convert; export without custom ops", n.name, n.domain, n.op_type);
    }
    Ok(())
}

/// The original decode with the head convolutions' outputs as its inputs.
fn decode_tail(model: &ModelProto, decoded: &str, levels: &BTreeMap<usize, Vec<HeadConv>>) -> Result<ModelProto> {
    let mut tail = model.clone();
    let g = tail.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?;
    let convs: Vec<&HeadConv> = levels.values().flatten().collect();
    let cut: std::collections::HashSet<usize> = convs.iter().map(|c| c.node).collect();
    crate::onnx::edit::remove_nodes(g, &cut);
    g.input.extend(convs.iter().map(|c| tensor_value_info(&c.output, DType::F32, &[1, c.channels, c.height, c.width])));
    g.output.retain(|o| o.name == decoded);
    crate::ir::rewrite::dce::eliminate(g)?;
    // The image input (and anything else only the backbone read) is no longer an input.
    let read: std::collections::HashSet<String> = g.node.iter().flat_map(|n| n.input.iter().cloned()).collect();
    g.input.retain(|v| read.contains(&v.name));
    if g.input.len() != convs.len() {
        bail!("the decode reads {} of the {} head convolution outputs; rknn-legalize cannot cut this head", g.input.len(), convs.len());
    }
    let mut known: std::collections::HashSet<&str> = g.input.iter().map(|v| v.name.as_str()).collect();
    known.extend(g.initializer.iter().map(|t| t.name.as_str()));
    known.extend(g.node.iter().flat_map(|n| n.output.iter().map(String::as_str)));
    if let Some(n) = g.node.iter().find(|n| n.input.iter().any(|i| !i.is_empty() && !known.contains(i.as_str()))) {
        bail!("the decode reads values from before the head convolutions (node '{}'); rknn-legalize cannot cut this head", n.name);
    }
    Ok(tail)
}

fn run_tail(tail: &mut TractRuntime, feeds: &[(String, Tensor)]) -> Result<Tensor> {
    Ok(tail.run(feeds)?.remove(0).1)
}

/// Zero logits for every head convolution output.
fn zero_logits(levels: &BTreeMap<usize, Vec<HeadConv>>) -> Vec<(String, Tensor)> {
    levels.values().flatten().map(|c| (c.output.clone(), Tensor::f32(vec![1, c.channels, c.height, c.width], vec![0.0; c.channels * c.height * c.width]))).collect()
}

/// Reads the layout off the original decode: with zero logits every sigmoid is 0.5 and every
/// DFL softmax uniform, so YOLOv5 rows hold ((x+0.5)·S, (y+0.5)·S, anchor w, anchor h) and
/// YOLOv8 columns ((x+0.5)·S, (y+0.5)·S, (R−1)·S, (R−1)·S). Anything else means the rows are
/// not in the order post-processing assumes, and the pass stops.
fn probe_layout(tail: &mut TractRuntime, zeros: &[(String, Tensor)], kind: HeadKind, classes: usize, reg_max: Option<usize>, levels: &BTreeMap<usize, Vec<HeadConv>>) -> Result<HeadLayout> {
    let out = run_tail(tail, zeros)?;
    let v = out.as_f32().ok_or_else(|| anyhow!("the decode's output is not float32"))?;
    let mut layout = HeadLayout { kind, classes, reg_max, levels: Vec::new(), offset: [0.0, 0.0] };
    let mut row = 0;
    let near = |a: f32, b: f32| (a - b).abs() <= 1e-3 * b.abs().max(1.0);
    // The first candidate's centre is half a stride in from the input's corner, unless the
    // model is cropped to a scene's ROI: then its grids carry the ROI's corner.
    let first = *levels.keys().next().ok_or_else(|| anyhow!("no head levels"))? as f32;
    let [ox, oy] = match kind {
        HeadKind::Yolov5Anchor => [v[0] - 0.5 * first, v[1] - 0.5 * first],
        _ => {
            let n = out.shape.get(2).copied().unwrap_or(1);
            [v[0] - 0.5 * first, v[n] - 0.5 * first]
        }
    };
    layout.offset = [ox.round(), oy.round()];
    for (&stride, convs) in levels {
        let c = &convs[0];
        let (h, w, s) = (c.height, c.width, stride as f32);
        let names = (format!("boxes_s{stride}"), format!("scores_s{stride}"), format!("score_sum_s{stride}"));
        let mut level = Level { stride, height: h, width: w, anchors: Vec::new(), boxes: names.0, scores: names.1, score_sum: None };
        match kind {
            HeadKind::Yolov5Anchor => {
                let no = 5 + classes;
                let [conv] = &convs[..] else { bail!("stride {stride} has {} head convolutions; a YOLOv5 head has one per stride", convs.len()) };
                if conv.channels % no != 0 {
                    bail!("head convolution at stride {stride} has {} channels, not anchors × (5 + {classes})", conv.channels);
                }
                let rows = |r: usize| &v[r * no..r * no + 4];
                if out.shape != [1, layout_rows(levels, no), no] {
                    bail!("the YOLOv5 decode outputs {:?}; expected [1, {}, {no}]", out.shape, layout_rows(levels, no));
                }
                for a in 0..conv.channels / no {
                    let r = rows(row + a * h * w);
                    level.anchors.push([r[2], r[3]]);
                    for (y, x) in (0..h).flat_map(|y| (0..w).map(move |x| (y, x))) {
                        let r = rows(row + a * h * w + y * w + x);
                        if !(near(r[0], (x as f32 + 0.5) * s + layout.offset[0]) && near(r[1], (y as f32 + 0.5) * s + layout.offset[1]) && near(r[2], level.anchors[a][0]) && near(r[3], level.anchors[a][1])) {
                            bail!("the YOLOv5 decode's rows at stride {stride} are not in (anchor, y, x) order; cannot split this head");
                        }
                    }
                }
                row += conv.channels / no * h * w;
            }
            HeadKind::Yolov8Dfl => {
                let r = reg_max.unwrap_or(16);
                let n = out.shape.get(2).copied().unwrap_or(0);
                if out.shape != [1, 4 + classes, n] || convs.len() != 2 || !convs.iter().any(|c| c.channels == 4 * r) || !convs.iter().any(|c| c.channels == classes) || 4 * r == classes {
                    bail!("stride {stride}: expected a {}-channel box and a {classes}-channel class convolution beside a [1, 4+{classes}, N] output", 4 * r);
                }
                for (y, x) in (0..h).flat_map(|y| (0..w).map(move |x| (y, x))) {
                    let col = |c: usize| v[c * n + row + y * w + x];
                    let span = (r - 1) as f32 * s;
                    if !(near(col(0), (x as f32 + 0.5) * s + layout.offset[0]) && near(col(1), (y as f32 + 0.5) * s + layout.offset[1]) && near(col(2), span) && near(col(3), span)) {
                        bail!("the YOLOv8 decode's columns at stride {stride} are not in (y, x) order; cannot split this head");
                    }
                }
                level.score_sum = Some(names.2.clone());
                row += h * w;
            }
            HeadKind::Raw => unreachable!("checked by the caller"),
        }
        layout.levels.push(level);
    }
    Ok(layout)
}

fn layout_rows(levels: &BTreeMap<usize, Vec<HeadConv>>, no: usize) -> usize {
    levels.values().map(|c| c[0].channels / no * c[0].height * c[0].width).sum()
}

/// Random head logits through the original decode (tract) and through the split tensors and
/// the Rust decode: the largest difference, relative to the value's magnitude.
fn check_decode(tail: &mut TractRuntime, layout: &HeadLayout, levels: &BTreeMap<usize, Vec<HeadConv>>) -> Result<f64> {
    let mut rng = crate::optics::rng::Rng::new(0x9e37_79b9);
    let mut feeds = Vec::new();
    let mut split = HashMap::new();
    for (level, convs) in layout.levels.iter().zip(levels.values()) {
        for c in convs {
            let n = c.channels * c.height * c.width;
            let logits: Vec<f32> = (0..n).map(|_| rng.range(-4.0, 4.0) as f32).collect();
            let t = Tensor::f32(vec![1, c.channels, c.height, c.width], logits);
            for (name, value) in split_values(layout, level, c, &t)? {
                split.insert(name, value);
            }
            feeds.push((c.output.clone(), t));
        }
    }
    let reference = run_tail(tail, &feeds)?;
    let ours = decode_dense(layout, &split)?;
    let (a, b) = (reference.as_f32().unwrap_or(&[]), ours.as_f32().unwrap_or(&[]));
    if reference.shape != ours.shape {
        bail!("the split decode gives {:?}, the original {:?}", ours.shape, reference.shape);
    }
    let worst = a.iter().zip(b).map(|(&x, &y)| ((x - y).abs() / x.abs().max(1.0)) as f64).fold(0.0, f64::max);
    // f32 rounding of pixel coordinates (≤ 640) and tract's exp/sigmoid approximations stay
    // near 1e-6 relative; a layout error is off by a cell, an anchor or a stride.
    if !(worst <= 1e-4) {
        bail!("the split head's decode differs from the original decode by {worst:.2e} (relative); not splitting");
    }
    Ok(worst)
}

/// What the legalized graph will output for `conv`'s logits `t` (the check's model of it).
fn split_values(layout: &HeadLayout, level: &Level, conv: &HeadConv, t: &Tensor) -> Result<Vec<(String, Tensor)>> {
    let sig = |t: Tensor| Tensor::f32(t.shape.clone(), t.as_f32().unwrap_or(&[]).iter().map(|&x| 1.0 / (1.0 + (-x).exp())).collect());
    let (h, w) = (conv.height, conv.width);
    Ok(match layout.kind {
        HeadKind::Yolov5Anchor => {
            let (box_rows, score_rows) = v5_rows(conv.channels, layout.classes);
            vec![
                (level.boxes.clone(), sig(t.select(1, &box_rows).ok_or_else(|| anyhow!("box rows"))?)),
                (level.scores.clone(), sig(t.select(1, &score_rows).ok_or_else(|| anyhow!("score rows"))?)),
            ]
        }
        _ if conv.channels == layout.classes => {
            let s = sig(t.clone());
            let v = s.as_f32().unwrap_or(&[]);
            let sum = (0..h * w).map(|i| (0..conv.channels).map(|c| v[c * h * w + i]).sum::<f32>().clamp(0.0, 1.0)).collect();
            let mut out = vec![(level.scores.clone(), s.clone())];
            if let Some(n) = &level.score_sum {
                out.push((n.clone(), Tensor::f32(vec![1, 1, h, w], sum)));
            }
            out
        }
        _ => vec![(level.boxes.clone(), t.clone())],
    })
}

/// YOLOv5 head rows: anchor a's channels are a·(5+nc) + (x, y, w, h, obj, classes…).
fn v5_rows(channels: usize, classes: usize) -> (Vec<usize>, Vec<usize>) {
    let no = 5 + classes;
    let anchors = channels / no;
    let boxes = (0..anchors).flat_map(|a| (0..4).map(move |j| a * no + j)).collect();
    let scores = (0..anchors).flat_map(|a| (4..no).map(move |j| a * no + j)).collect();
    (boxes, scores)
}

/// Rewrites one stride's head convolutions into its split outputs.
#[allow(clippy::too_many_arguments)]
fn split_level(g: &mut GraphProto, opset: i64, kind: HeadKind, classes: usize, level: &Level, convs: &[HeadConv], score_sum: bool, outputs: &mut Vec<crate::onnx::proto::ValueInfoProto>) -> Result<()> {
    let (h, w) = (level.height, level.width);
    let declare = |outputs: &mut Vec<_>, name: &str, c: usize| outputs.push(tensor_value_info(name, DType::F32, &[1, c, h, w]));
    match kind {
        HeadKind::Yolov5Anchor => {
            let conv = &convs[0];
            let (box_rows, score_rows) = v5_rows(conv.channels, classes);
            let logits = sub_conv(g, conv.node, &box_rows, "boxes")?;
            push_node(g, "Sigmoid", vec![logits], &level.boxes, vec![]);
            declare(outputs, &level.boxes, box_rows.len());
            let logits = sub_conv(g, conv.node, &score_rows, "scores")?;
            push_node(g, "Sigmoid", vec![logits], &level.scores, vec![]);
            declare(outputs, &level.scores, score_rows.len());
        }
        _ => {
            for c in convs {
                if c.channels == classes {
                    push_node(g, "Sigmoid", vec![c.output.clone()], &level.scores, vec![]);
                    declare(outputs, &level.scores, classes);
                    if let (true, Some(sum_name)) = (score_sum, &level.score_sum) {
                        let summed = fresh_name(g, &format!("{}_unclipped", sum_name));
                        let mut inputs = vec![level.scores.clone()];
                        let mut attrs = vec![attr::make_int("keepdims", 1)];
                        if opset >= 13 {
                            inputs.push(constant(g, &format!("{sum_name}_axes"), Tensor::new(vec![1], crate::tensor::TensorData::I64(vec![1]))));
                        } else {
                            attrs.push(attr::make_ints("axes", vec![1]));
                        }
                        push_node(g, "ReduceSum", inputs, &summed, attrs);
                        let lo = constant(g, &format!("{sum_name}_min"), Tensor::f32(vec![], vec![0.0]));
                        let hi = constant(g, &format!("{sum_name}_max"), Tensor::f32(vec![], vec![1.0]));
                        push_node(g, "Clip", vec![summed, lo, hi], sum_name, vec![]);
                        declare(outputs, sum_name, 1);
                    }
                } else {
                    rename_value(g, &c.output, &level.boxes);
                    declare(outputs, &level.boxes, c.channels);
                }
            }
        }
    }
    Ok(())
}

/// A copy of convolution `node` computing only output channels `rows`; returns its output.
fn sub_conv(g: &mut GraphProto, node: usize, rows: &[usize], part: &str) -> Result<String> {
    let n = g.node[node].clone();
    let mut inputs = vec![n.input[0].clone()];
    for (i, what) in [(1, "weight"), (2, "bias")] {
        let Some(name) = n.input.get(i).filter(|s| !s.is_empty()) else { continue };
        let t = crate::onnx::edit::initializer(g, name).ok_or_else(|| anyhow!("head convolution '{}' has non-constant input '{name}'", n.name))?;
        let rows_of = to_tensor(t)?.select(0, rows).ok_or_else(|| anyhow!("cannot take rows of '{}'s {what}", n.name))?;
        inputs.push(constant(g, &format!("{}.{part}.{what}", n.name), rows_of));
    }
    let out = fresh_name(g, &format!("{}/{part}_logits", n.name));
    let mut conv = n.clone();
    conv.name = format!("{}/{part}", n.name);
    conv.input = inputs;
    conv.output = vec![out.clone()];
    g.node.push(conv);
    Ok(out)
}

fn constant(g: &mut GraphProto, base: &str, t: Tensor) -> String {
    let name = fresh_name(g, base);
    g.initializer.push(from_tensor(&name, &t));
    name
}

fn push_node(g: &mut GraphProto, op: &str, input: Vec<String>, output: &str, attribute: Vec<AttributeProto>) {
    let name = format!("{output}/{op}");
    g.node.push(NodeProto { op_type: op.into(), name, input, output: vec![output.into()], attribute, ..Default::default() });
}

/// Renames a value everywhere it is produced or read.
fn rename_value(g: &mut GraphProto, from: &str, to: &str) {
    for n in &mut g.node {
        for v in n.input.iter_mut().chain(n.output.iter_mut()).filter(|v| *v == from) {
            *v = to.to_string();
        }
    }
    g.value_info.retain(|v| v.name != from);
}

/// What the RK3588 NPU may not take as is; rknn-convert's placement table is the final word.
fn npu_notes(g: &GraphProto) -> Result<Vec<String>> {
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let mut notes = Vec::new();
    for n in &g.node {
        match n.op_type.as_str() {
            "Conv" | "MaxPool" | "AveragePool" => {
                let k = attr::ints(n, "kernel_shape").unwrap_or_default();
                if k.iter().any(|&k| k > COMMON_KERNEL) {
                    let depthwise = attr::int(n, "group", 1) > 1 && n.op_type == "Conv";
                    notes.push(format!("{} '{}' has a {k:?} kernel{}: kept, not split", n.op_type, n.name, if depthwise { " (depthwise)" } else { "" }));
                }
            }
            "Resize" | "Upsample" => {
                let mode = attr::string(n, "mode", "nearest");
                if mode != "nearest" && mode != "linear" {
                    notes.push(format!("{} '{}' uses mode '{mode}', which the NPU may run on the CPU", n.op_type, n.name));
                }
            }
            "Concat" | "Split" => {
                let parts = if n.op_type == "Concat" { &n.input } else { &n.output };
                let channels: Vec<usize> = parts.iter().filter_map(|v| inf.shape(v)).filter(|s| s.len() == 4).map(|s| s[1]).collect();
                if attr::int(n, "axis", 0) == 1 && channels.iter().any(|c| c % CHANNEL_ALIGN != 0) {
                    notes.push(format!("{} '{}' has channel parts {channels:?}, not all multiples of {CHANNEL_ALIGN} (prune with round_to: 16 where it can choose)", n.op_type, n.name));
                }
            }
            _ => {}
        }
    }
    Ok(notes)
}
