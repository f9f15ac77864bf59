//! What the trainer matches: the head values of a detector and how to read their channels,
//! and the features the head branches start from, as the worker's JSON specs.

use crate::analysis::channels::detector_convolutions;
use crate::analysis::head::{self, HeadKind};
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use anyhow::{anyhow, bail, Result};
use std::collections::HashMap;

/// The head convolutions to distil and how to read their channels, for the worker.
pub fn head_specs(model: &ModelProto) -> Result<Vec<serde_json::Value>> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
    let head = head::detect(&graph, &inf, &outputs);
    let nc = head.classes.ok_or_else(|| anyhow!("recover needs a YOLOv5 or YOLOv8 head with a known class count"))?;
    let mut specs = Vec::new();
    for i in detector_convolutions(&graph) {
        let n = graph.node(i);
        let channels = n.input.get(1).and_then(|w| graph.initializers.get(w.as_str())).and_then(|w| w.dims.first()).copied().unwrap_or(0) as usize;
        let value = n.output[0].clone();
        let spec = match head.kind {
            HeadKind::Yolov5Anchor if channels.is_multiple_of(5 + nc) => serde_json::json!({"value": value, "kind": "v5", "anchors": channels / (5 + nc), "outputs": 5 + nc}),
            HeadKind::Yolov8Dfl if Some(channels) == head.reg_max.map(|r| 4 * r) => serde_json::json!({"value": value, "kind": "v8box", "reg_max": head.reg_max}),
            HeadKind::Yolov8Dfl if channels == nc => serde_json::json!({"value": value, "kind": "v8cls"}),
            _ => bail!("head convolution '{}' ({channels} channels) does not fit a {:?} head with {nc} classes; recover cannot read it", n.name, head.kind),
        };
        specs.push(spec);
    }
    if specs.is_empty() {
        bail!("no head convolutions found; recover needs a detector ending in convolutions");
    }
    Ok(specs)
}

/// `head_specs` of a student distilled from a teacher it was cut from: each head
/// convolution a scene dropped rows from reads the teacher's kept rows.
pub fn head_specs_against(student: &ModelProto, kept: &HashMap<String, Vec<usize>>) -> Result<Vec<serde_json::Value>> {
    let mut heads = head_specs(student)?;
    for h in &mut heads {
        if let Some(k) = h["value"].as_str().and_then(|v| kept.get(v)) {
            h["keep"] = serde_json::json!(k);
        }
    }
    Ok(heads)
}

/// The head values of a model from rknn-legalize (per-stride boxes and scores), for the
/// worker: each output's logits (a Sigmoid's input), YOLOv8's box distributions as they are.
/// `student_value` names the student's copy of a value where it differs (a quantized model's
/// dequantized value).
pub fn split_head_specs(model: &ModelProto, student_value: &std::collections::BTreeMap<String, String>) -> Result<Vec<serde_json::Value>> {
    use crate::detect::split_head::HeadLayout;
    let layout = HeadLayout::from_model(model)?;
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let logits = |out: &str| -> String {
        match g.node.iter().find(|n| n.output.iter().any(|o| o == out)) {
            Some(n) if n.op_type == "Sigmoid" => n.input[0].clone(),
            _ => out.to_string(),
        }
    };
    let spec = |value: String, rest: serde_json::Value| {
        let mut s = serde_json::json!({"value": value, "student_value": student_value.get(&value)});
        if let (Some(a), Some(b)) = (s.as_object_mut(), rest.as_object()) {
            a.extend(b.clone());
        }
        s
    };
    let nc = layout.classes;
    let mut specs = Vec::new();
    for l in &layout.levels {
        match layout.kind {
            HeadKind::Yolov5Anchor => {
                let na = l.anchors.len();
                specs.push(spec(logits(&l.boxes), serde_json::json!({"kind": "v5box", "anchors": na})));
                specs.push(spec(logits(&l.scores), serde_json::json!({"kind": "v5scores", "anchors": na, "outputs": 1 + nc})));
            }
            HeadKind::Yolov8Dfl => {
                specs.push(spec(l.boxes.clone(), serde_json::json!({"kind": "v8box", "reg_max": layout.reg_max})));
                specs.push(spec(logits(&l.scores), serde_json::json!({"kind": "v8cls"})));
            }
            ref other => bail!("a {other:?} head cannot be distilled"),
        }
    }
    Ok(specs)
}

/// The head convolutions' inputs and the neck outputs their branches start from, matched
/// channel by channel: a pruned value's kept positions index the teacher's channels (a dense
/// signal where the logits are sparse).
pub fn feature_specs(model: &ModelProto, kept: &HashMap<String, Vec<usize>>) -> Result<Vec<serde_json::Value>> {
    let graph = Graph::build(model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?)?;
    let inputs: Vec<String> = detector_convolutions(&graph).into_iter().map(|i| graph.node(i).input[0].clone()).collect();
    let mut values: Vec<String> = inputs.iter().filter_map(|v| branch_root(&graph, v)).chain(inputs.iter().cloned()).collect();
    values.sort();
    values.dedup();
    Ok(values.into_iter().map(|v| serde_json::json!({ "value": v, "keep": kept.get(&v) })).collect())
}

/// Where the head branch ending in value `v` starts: up through the branch's own
/// convolutions (each value read by one convolution, SiLU pairs looked through) to the first
/// value several convolutions read, the neck output a YOLOv8 head's box and class branches
/// share. None when `v` is that already (a YOLOv5 head reads the neck directly).
fn branch_root(g: &Graph, v: &str) -> Option<String> {
    let conv_readers = |v: &str| g.consumers_of(v).iter().filter(|&&c| g.node(c).op_type == "Conv").count();
    let mut v = v.to_string();
    // Heads are a few convolutions deep: a longer walk has left the head.
    for _ in 0..4 {
        if conv_readers(&v) != 1 {
            return None;
        }
        let p = g.producer_of(&v)?;
        let x = if p.op_type == "Mul" { p.input[0].as_str() } else { v.as_str() };
        let conv = g.producer_of(x).filter(|n| n.op_type == "Conv")?;
        let u = conv.input[0].clone();
        if conv_readers(&u) > 1 {
            return Some(u);
        }
        v = u;
    }
    None
}

