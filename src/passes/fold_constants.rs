//! `fold-constants`: every node whose inputs are all known is evaluated once, at compile time.
//!
//! "Known" means initializers, Constant outputs, and the shapes of values whose shape is
//! static (PyTorch's Shape -> Gather -> Unsqueeze -> Concat -> Reshape chains). The constant
//! subgraph is evaluated by ONNX Runtime itself, so folded values carry ORT's semantics
//! exactly (Resize coordinate modes, Clip bounds, integer division...).
//! Needs: ONNX Runtime. Guarantees: no node left whose inputs are all constant; every
//! value's shape static when the graph inputs' are (written to value_info).
//! Reports: nodes folded, values materialized, bytes added, values still without a static shape.

use crate::ir::rewrite::value_info::write_value_info;
use crate::ir::{infer, Graph};
use crate::onnx::proto::{GraphProto, ModelProto, NodeProto, ValueInfoProto};
use crate::onnx::tensor_proto::from_tensor;
use super::{Pass, PassContext};
use crate::runtime::{ort_runtime::OrtRuntime, Runtime};
use anyhow::{Context, Result};
use std::collections::{HashMap, HashSet};

/// Ops whose output differs from run to run: never folded.
const NONDETERMINISTIC: &[&str] = &["RandomUniform", "RandomNormal", "RandomUniformLike", "RandomNormalLike", "Multinomial", "Bernoulli"];

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// Values larger than this stay computed at run time: folding must not bloat the file.
    /// 4 M elements (16 MB of f32) is well above a gate map at 1/4 scale of 640x480.
    pub max_elements: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options { max_elements: 4 << 20 }
    }
}

pub struct FoldConstants {
    pub options: Options,
}

impl Pass for FoldConstants {
    fn name(&self) -> &'static str {
        "fold-constants"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let plan = plan(model, self.options.max_elements)?;
        let mut bytes_added = 0usize;
        if !plan.frontier.is_empty() {
            let eval = evaluation_model(model, &plan);
            let mut ort = OrtRuntime::new(&eval).context("evaluating the constant subgraph")?;
            let values = ort.run(&[]).context("evaluating the constant subgraph")?;
            let g = super::graph_mut(model)?;
            crate::onnx::edit::remove_nodes(g, &plan.foldable);
            for (name, t) in values {
                let p = from_tensor(&name, &t);
                bytes_added += p.raw_data.len();
                crate::onnx::edit::set_initializer(g, p);
            }
        }
        let g = super::graph_mut(model)?;
        crate::ir::rewrite::dce::eliminate(g)?;
        let not_static = write_value_info(g)?;
        Ok(serde_json::json!({
            "nodes_folded": plan.foldable.len(),
            "values_materialized": plan.frontier.len(),
            "bytes_added": bytes_added,
            "values_without_static_shape": not_static,
        }))
    }
}

struct Plan {
    foldable: HashSet<usize>,
    /// Constant values read by run-time nodes or graph outputs: what gets materialized.
    frontier: Vec<String>,
    /// Shape/Size outputs known from static shapes (their inputs are not constant).
    shape_values: HashMap<String, crate::tensor::Tensor>,
}

fn plan(model: &ModelProto, max_elements: usize) -> Result<Plan> {
    let g = model.graph.as_ref().expect("checked by the pipeline");
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    // An initializer also listed as an input can be overridden by the caller: not constant.
    let overridable: HashSet<&str> = g.input.iter().map(|v| v.name.as_str()).collect();
    let mut constant: HashSet<&str> = g.initializer.iter().map(|t| t.name.as_str()).filter(|n| !overridable.contains(n)).collect();
    let mut foldable = HashSet::new();
    let mut shape_values = HashMap::new();
    for &i in &graph.order {
        let n = graph.node(i);
        let standard = n.domain.is_empty() || n.domain == "ai.onnx";
        let has_subgraph = n.attribute.iter().any(|a| a.g.is_some() || !a.graphs.is_empty());
        if !standard || has_subgraph || NONDETERMINISTIC.contains(&n.op_type.as_str()) {
            continue;
        }
        let too_big = n.output.iter().any(|o| inf.shape(o).is_some_and(|s| s.iter().product::<usize>() > max_elements));
        let known_shape = matches!(n.op_type.as_str(), "Shape" | "Size") && shape_value(n, &inf).is_some();
        let inputs_const = n.input.iter().filter(|s| !s.is_empty()).all(|s| constant.contains(s.as_str()));
        if too_big || !(known_shape || inputs_const) {
            continue;
        }
        if known_shape && !inputs_const {
            shape_values.insert(n.output[0].clone(), shape_value(n, &inf).expect("checked"));
        }
        foldable.insert(i);
        constant.extend(n.output.iter().filter(|o| !o.is_empty()).map(|o| o.as_str()));
    }
    let outputs: HashSet<&str> = g.output.iter().map(|o| o.name.as_str()).collect();
    let mut frontier: Vec<String> = Vec::new();
    for &i in &foldable {
        for o in g.node[i].output.iter().filter(|o| !o.is_empty()) {
            let read_at_run_time = graph.consumers_of(o).iter().any(|c| !foldable.contains(c));
            if read_at_run_time || outputs.contains(o.as_str()) {
                frontier.push(o.clone());
            }
        }
    }
    frontier.sort();
    Ok(Plan { foldable, frontier, shape_values })
}

fn shape_value(n: &NodeProto, inf: &crate::ir::Inferred) -> Option<crate::tensor::Tensor> {
    use crate::tensor::{Tensor, TensorData};
    match n.op_type.as_str() {
        "Shape" => inf.consts.get(&n.output[0]).cloned(),
        "Size" => inf.shape(&n.input[0]).map(|s| Tensor::new(vec![], TensorData::I64(vec![s.iter().product::<usize>() as i64]))),
        _ => None,
    }
}

/// A model computing exactly the frontier values from the foldable nodes.
fn evaluation_model(model: &ModelProto, plan: &Plan) -> ModelProto {
    let g = model.graph.as_ref().expect("checked by the pipeline");
    let mut nodes = Vec::new();
    for (_, n) in g.node.iter().enumerate().filter(|(i, _)| plan.foldable.contains(i)) {
        match plan.shape_values.get(&n.output[0]) {
            Some(t) => nodes.push(NodeProto {
                op_type: "Constant".into(),
                output: vec![n.output[0].clone()],
                attribute: vec![crate::onnx::proto::AttributeProto {
                    name: "value".into(),
                    r#type: crate::onnx::proto::AttributeType::Tensor as i32,
                    t: Some(from_tensor("", t)),
                    ..Default::default()
                }],
                ..Default::default()
            }),
            None => nodes.push(n.clone()),
        }
    }
    let read: HashSet<&str> = nodes.iter().flat_map(|n| n.input.iter().map(|s| s.as_str())).collect();
    let graph = GraphProto {
        name: "fold_constants".into(),
        initializer: g.initializer.iter().filter(|t| read.contains(t.name.as_str())).cloned().collect(),
        output: plan.frontier.iter().map(|n| ValueInfoProto { name: n.clone(), ..Default::default() }).collect(),
        node: nodes,
        ..Default::default()
    };
    ModelProto { ir_version: model.ir_version, opset_import: model.opset_import.clone(), graph: Some(graph), ..Default::default() }
}

