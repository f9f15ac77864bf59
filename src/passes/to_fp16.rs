//! `fp16`: half-precision weights, and (by default) activations.
//!
//! Needs: a float graph (the lossless passes first). Activation mode needs calibration
//! frames (`--calib`, or simulated) to find values whose range would overflow f16.
//! Guarantees: inputs and outputs stay float32; the detection decode after the head
//! convolutions stays float32 (pixel coordinates up to 640 would round to 0.5 px in f16);
//! any node whose calibrated output, or any weight, exceeds f16's safe range stays float32,
//! with Casts at the borders; Resize's float32-only inputs are left float32.
//! Reports: nodes in f16 and f32 (with why), initializers converted, weights that would
//! overflow or flush to zero.

use crate::analysis::channels::head_convolutions;
use crate::calib_frames::image_feeds;
use crate::ir::{infer, Graph};
use crate::onnx::edit::{fresh_name, set_initializer};
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::{AttributeProto, ModelProto, TypeValue};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use super::{Pass, PassContext};
use crate::quant::collect::statistics;
use crate::quant::qdq::node;
use crate::tensor::{DType, Tensor, TensorData};
use anyhow::{anyhow, Result};
use half::f16;
use std::collections::{BTreeMap, HashMap, HashSet};

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// Compute in f16 too; false stores weights in f16 and computes in f32.
    pub activations: bool,
    /// Frames that measure activation ranges (activation mode).
    pub calib_frames: usize,
    /// A value whose calibrated |max| exceeds this fraction of f16's largest finite value
    /// (65504) keeps its node in f32: unseen frames may be brighter than calibration.
    pub headroom: f64,
    /// Nodes (or their output values) to keep in f32.
    pub keep_float: Vec<String>,
    /// Seed of the simulated calibration frames (when no `--calib`).
    pub seed: u64,
}

impl Default for Options {
    fn default() -> Self {
        Options { activations: true, calib_frames: 8, headroom: 0.25, keep_float: Vec::new(), seed: 0 }
    }
}

pub struct ToFp16 {
    pub options: Options,
}

/// f16's largest finite value.
const F16_MAX: f64 = 65504.0;
/// Ops computed in f16 (every float input and output of theirs is f16).
const F16_OPS: &[&str] = &[
    "Conv", "ConvTranspose", "Add", "Sub", "Mul", "Div", "Sigmoid", "Relu", "LeakyRelu", "HardSigmoid", "HardSwish", "Tanh", "Clip", "Concat", "MaxPool", "AveragePool",
    "GlobalAveragePool", "Split", "Slice", "Resize", "Reshape", "Transpose", "Softmax", "Identity", "BatchNormalization",
];

impl Pass for ToFp16 {
    fn name(&self) -> &'static str {
        "fp16"
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let o = &self.options;
        let src = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?.clone();
        let graph = Graph::build(&src)?;
        let inf = infer(&graph);
        let dtype_of = |v: &str| match graph.initializers.get(v) {
            Some(t) => DType::from_onnx(t.data_type),
            None => inf.types.get(v).and_then(|t| t.dtype),
        };
        let is_f32 = |v: &str| dtype_of(v) == Some(DType::F32);

        // Weights: convertible unless a value overflows f16.
        let mut overflowing: HashSet<&str> = HashSet::new();
        let mut flushed = 0usize;
        for (name, t) in &graph.initializers {
            if t.data_type != DType::F32.onnx_code() {
                continue;
            }
            let v = to_tensor(t)?;
            let v = v.as_f32().expect("f32");
            if v.iter().any(|x| x.is_finite() && (*x as f64).abs() > F16_MAX) {
                overflowing.insert(name);
            }
            flushed += v.iter().filter(|&&x| x != 0.0 && f16::from_f32(x) == f16::ZERO).count();
        }

        let mut why_f32: BTreeMap<usize, String> = BTreeMap::new();
        let mut region: HashSet<usize> = HashSet::new();
        let mut range_source = None;
        if o.activations {
            let tail = graph.downstream_of(&head_convolutions(&graph).into_iter().collect());
            let keep: HashSet<&str> = o.keep_float.iter().map(String::as_str).collect();
            for &i in &graph.order {
                let n = graph.node(i);
                let reason = if tail.contains(&i) {
                    Some("detection decode (pixel coordinates need f32)".to_string())
                } else if keep.contains(n.name.as_str()) || n.output.iter().any(|v| keep.contains(v.as_str())) {
                    Some("keep_float".to_string())
                } else if !n.domain.is_empty() || !F16_OPS.contains(&n.op_type.as_str()) {
                    Some(format!("{} is not converted", n.op_type))
                } else if let Some(w) = n.input.iter().find(|v| overflowing.contains(v.as_str())) {
                    Some(format!("weight '{w}' exceeds f16's range"))
                } else if !n.output.iter().filter(|v| !v.is_empty()).all(|v| is_f32(v)) {
                    Some("an output is not float32".to_string())
                } else if n.input.iter().filter(|v| !v.is_empty()).any(|v| dtype_of(v).is_none()) {
                    // Casting needs to know which inputs are float.
                    Some("an input's type is unknown".to_string())
                } else {
                    None
                };
                match reason {
                    Some(r) => {
                        why_f32.insert(i, r);
                    }
                    None => {
                        region.insert(i);
                    }
                }
            }
            // Calibrated ranges: values beyond the headroom keep their node in f32.
            let values: Vec<String> = region.iter().flat_map(|&i| graph.node(i).output.iter().filter(|v| !v.is_empty()).cloned()).collect();
            let (feeds, source) = image_feeds(&graph, &inf, cx.calib.as_deref(), o.calib_frames.max(1), o.seed)?;
            let hists = statistics(model, &values, &HashMap::new(), &feeds, std::thread::available_parallelism().map_or(1, |n| n.get()))?.histograms;
            range_source = Some(source);
            let limit = F16_MAX * o.headroom;
            let candidates: Vec<usize> = graph.order.iter().copied().filter(|i| region.contains(i)).collect();
            for i in candidates {
                let n = graph.node(i);
                if let Some((v, peak)) = n.output.iter().filter_map(|v| hists.get(v).map(|h| (v, h.min.abs().max(h.max.abs())))).find(|(_, p)| *p > limit || !p.is_finite()) {
                    region.remove(&i);
                    why_f32.insert(i, format!("'{v}' reaches {peak:.1} on the calibration frames (f16 limit with headroom {limit:.0})"));
                }
            }
        }

        let mut g = src.clone();
        let mut f16_name: HashMap<String, String> = HashMap::new();
        let mut f32_name: HashMap<String, String> = HashMap::new();
        let outputs: HashSet<String> = src.output.iter().map(|o| o.name.clone()).collect();
        let produced_in_region = |v: &str| graph.producer.get(v).is_some_and(|p| region.contains(p));
        let mut casts = Vec::new();
        let mut converted = 0usize;

        // Weights-only mode: float32 initializers become f16 initializers behind a Cast.
        if !o.activations {
            for t in &src.initializer {
                if t.data_type != DType::F32.onnx_code() || overflowing.contains(t.name.as_str()) {
                    continue;
                }
                let value = to_tensor(t)?;
                if value.len() < 2 {
                    continue;
                }
                let h = fresh_name(&g, &format!("{}_fp16", t.name));
                set_initializer(&mut g, from_tensor(&h, &to_f16(&value)));
                g.initializer.retain(|x| x.name != t.name);
                g.input.retain(|x| x.name != t.name);
                casts.push(node("Cast", &format!("{}_to_f32", t.name), vec![h], vec![t.name.clone()], vec![to_attr(DType::F32)]));
                converted += 1;
            }
        }

        for &i in &graph.order {
            let n = graph.node(i);
            let in_region = region.contains(&i);
            for (s, v) in n.input.iter().enumerate() {
                if v.is_empty() || !is_f32(v) || (n.op_type == "Resize" && s > 0) {
                    continue;
                }
                let name = if in_region {
                    if produced_in_region(v) {
                        continue;
                    }
                    if !f16_name.contains_key(v) {
                        let h = fresh_name(&g, &format!("{v}_fp16"));
                        if let Some(t) = graph.initializers.get(v.as_str()) {
                            set_initializer(&mut g, from_tensor(&h, &to_f16(&to_tensor(t)?)));
                            converted += 1;
                        } else {
                            casts.push(node("Cast", &format!("{v}_to_f16"), vec![v.clone()], vec![h.clone()], vec![to_attr(DType::F16)]));
                        }
                        f16_name.insert(v.clone(), h);
                    }
                    f16_name[v].clone()
                } else {
                    if !produced_in_region(v) {
                        continue;
                    }
                    if !f32_name.contains_key(v) {
                        let h = fresh_name(&g, &format!("{v}_fp32"));
                        casts.push(node("Cast", &format!("{v}_to_f32"), vec![region_value(v, &outputs)], vec![h.clone()], vec![to_attr(DType::F32)]));
                        f32_name.insert(v.clone(), h);
                    }
                    f32_name[v].clone()
                };
                g.node[i].input[s] = name;
            }
            if in_region {
                for (k, v) in n.output.iter().enumerate() {
                    if outputs.contains(v) {
                        g.node[i].output[k] = region_value(v, &outputs);
                        casts.push(node("Cast", &format!("{v}_output_to_f32"), vec![region_value(v, &outputs)], vec![v.clone()], vec![to_attr(DType::F32)]));
                    }
                    if !v.is_empty() {
                        // Region consumers read the f16 value.
                        for &c in graph.consumers_of(v) {
                            if region.contains(&c) {
                                for x in g.node[c].input.iter_mut().filter(|x| *x == v) {
                                    *x = region_value(v, &outputs);
                                }
                            }
                        }
                    }
                }
            }
        }
        // Declared types follow: values made in f16 are float16.
        let region_values: HashSet<String> = region.iter().flat_map(|&i| graph.node(i).output.iter().cloned()).filter(|v| !outputs.contains(v)).collect();
        for vi in &mut g.value_info {
            if region_values.contains(&vi.name) {
                if let Some(TypeValue::TensorType(t)) = vi.r#type.as_mut().and_then(|t| t.value.as_mut()) {
                    t.elem_type = DType::F16.onnx_code();
                }
            }
        }
        g.node.extend(casts);
        sort_topologically(&mut g)?;
        model.graph = Some(g);
        crate::ir::rewrite::dce::eliminate(crate::passes::graph_mut(model)?)?;
        let f32_nodes: Vec<serde_json::Value> = why_f32.iter().map(|(&i, w)| serde_json::json!({"node": graph.node(i).name, "op": graph.node(i).op_type, "why": w})).collect();
        Ok(serde_json::json!({
            "activations": o.activations,
            "nodes_f16": region.len(),
            "nodes_f32": f32_nodes,
            "initializers_converted": converted,
            "weights_overflowing_f16": overflowing.len(),
            "weights_flushed_to_zero": flushed,
            "range_frames": range_source,
        }))
    }
}

/// The name of `v`'s f16 value inside the region (graph outputs keep their names for the
/// float32 copy).
fn region_value(v: &str, outputs: &HashSet<String>) -> String {
    if outputs.contains(v) { format!("{v}_fp16") } else { v.to_string() }
}

fn to_f16(t: &Tensor) -> Tensor {
    let v = t.as_f32().expect("f32 initializer");
    Tensor::new(t.shape.clone(), TensorData::F16(v.iter().map(|&x| f16::from_f32(x)).collect()))
}

fn to_attr(to: DType) -> AttributeProto {
    AttributeProto { name: "to".into(), i: Some(to.onnx_code() as i64), r#type: 2, ..Default::default() }
}
