//! Small model edits shared by runtimes and passes.

use super::proto::{ModelProto, ValueInfoProto};

/// A copy of `model` that also outputs each of `names` (intermediate values become observable).
pub fn expose_outputs(model: &ModelProto, names: &[String]) -> ModelProto {
    let mut m = model.clone();
    if let Some(g) = m.graph.as_mut() {
        for n in names {
            if !g.output.iter().any(|o| &o.name == n) {
                let known = g.value_info.iter().find(|v| &v.name == n).cloned();
                g.output.push(known.unwrap_or(ValueInfoProto { name: n.clone(), ..Default::default() }));
            }
        }
    }
    m
}

use super::proto::{GraphProto, TensorProto};
use std::collections::HashSet;

/// The initializer called `name`.
pub fn initializer<'g>(g: &'g GraphProto, name: &str) -> Option<&'g TensorProto> {
    g.initializer.iter().find(|t| t.name == name)
}

/// Adds (or replaces) an initializer.
pub fn set_initializer(g: &mut GraphProto, t: TensorProto) {
    match g.initializer.iter_mut().find(|x| x.name == t.name) {
        Some(slot) => *slot = t,
        None => g.initializer.push(t),
    }
}

/// Makes input `slot` of node `node` a new initializer holding `t`, named after the value it
/// replaces plus `tag`. The name is fresh because the old constant may be shared with
/// another node; a missing optional input (a conv without bias) is added.
pub fn set_input_constant(g: &mut GraphProto, node: usize, slot: usize, t: &crate::tensor::Tensor, tag: &str) {
    let n = &g.node[node];
    let old = match n.input.get(slot).filter(|s| !s.is_empty()) {
        Some(v) => v.clone(),
        None => format!("{}_input{slot}", if n.name.is_empty() { &n.op_type } else { &n.name }),
    };
    let name = fresh_name(g, &format!("{old}_{tag}"));
    set_initializer(g, super::tensor_proto::from_tensor(&name, t));
    let n = &mut g.node[node];
    if n.input.len() <= slot {
        n.input.resize(slot + 1, String::new());
    }
    n.input[slot] = name;
}

/// Puts `t` in place of the initializer `name`, under a fresh name from `base`, when only one
/// node reads it and it is no graph input or output (so that a rewrite and its inverse give
/// back the same model, byte for byte); beside it otherwise. Returns the new name.
pub fn swap_initializer(g: &mut GraphProto, name: &str, base: &str, mut t: TensorProto) -> String {
    let readers = g.node.iter().flat_map(|n| &n.input).filter(|i| *i == name).count();
    t.name = fresh_name(g, base);
    let new = t.name.clone();
    match g.initializer.iter().position(|x| x.name == name) {
        Some(at) if readers == 1 && !g.output.iter().chain(&g.input).any(|v| v.name == name) => g.initializer[at] = t,
        _ => g.initializer.push(t),
    }
    new
}

/// The one node that reads `v`, when exactly one does and `v` is no graph output.
pub fn only_reader(g: &GraphProto, v: &str) -> Option<usize> {
    let r: Vec<usize> = (0..g.node.len()).filter(|&j| g.node[j].input.iter().any(|i| i == v)).collect();
    (r.len() == 1 && !g.output.iter().any(|o| o.name == v)).then(|| r[0])
}

/// A value name not used anywhere in `g`, derived from `base`.
pub fn fresh_name(g: &GraphProto, base: &str) -> String {
    let used: HashSet<&str> = g
        .node
        .iter()
        .flat_map(|n| n.input.iter().chain(&n.output))
        .chain(g.initializer.iter().map(|t| &t.name))
        .chain(g.input.iter().chain(&g.output).map(|v| &v.name))
        .map(|s| s.as_str())
        .collect();
    (0..).map(|i| if i == 0 { base.to_string() } else { format!("{base}_{i}") }).find(|n| !used.contains(n.as_str())).expect("unbounded")
}

/// Adds `t` as an initializer under a fresh name derived from `base`; returns the name.
pub fn add_constant(g: &mut GraphProto, base: &str, t: &crate::tensor::Tensor) -> String {
    let name = fresh_name(g, base);
    g.initializer.push(crate::onnx::tensor_proto::from_tensor(&name, t));
    name
}

/// Makes every reader of `from` read `to` instead (graph outputs keep their names: when
/// `from` is a graph output, the value `to` is renamed to `from` where it is produced).
/// Returns false, changing nothing, when that rename is impossible (`to` is an input,
/// an initializer or itself a graph output).
pub fn replace_value(g: &mut GraphProto, from: &str, to: &str) -> bool {
    let from_is_output = g.output.iter().any(|o| o.name == from);
    if !from_is_output {
        for n in &mut g.node {
            for i in n.input.iter_mut().filter(|i| *i == from) {
                *i = to.to_string();
            }
        }
        return true;
    }
    let to_is_fixed = g.input.iter().chain(&g.output).any(|v| v.name == to) || g.initializer.iter().any(|t| t.name == to);
    if to_is_fixed {
        return false;
    }
    // `from` must stop being produced by its old producer before `to` takes its name.
    for n in &mut g.node {
        for o in n.output.iter_mut().filter(|o| *o == from) {
            *o = String::new();
        }
    }
    for n in &mut g.node {
        for v in n.input.iter_mut().chain(n.output.iter_mut()).filter(|v| *v == to || *v == from) {
            *v = from.to_string();
        }
    }
    g.value_info.retain(|v| v.name != to);
    true
}

/// Removes the nodes whose indices are in `dead`.
pub fn remove_nodes(g: &mut GraphProto, dead: &HashSet<usize>) {
    let mut i = 0;
    g.node.retain(|_| {
        let keep = !dead.contains(&i);
        i += 1;
        keep
    });
}


/// A value's declaration with a static shape.
pub fn tensor_value_info(name: &str, dtype: crate::tensor::DType, shape: &[usize]) -> crate::onnx::proto::ValueInfoProto {
    use crate::onnx::proto::{Dimension, DimensionValue, TensorShapeProto, TensorTypeProto, TypeProto, TypeValue};
    let dim = shape.iter().map(|&d| Dimension { value: Some(DimensionValue::DimValue(d as i64)), denotation: String::new() }).collect();
    crate::onnx::proto::ValueInfoProto {
        name: name.to_string(),
        r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: dtype.onnx_code(), shape: Some(TensorShapeProto { dim }) })), denotation: String::new() }),
        ..Default::default()
    }
}

/// The model's default-domain ("" or "ai.onnx") opset version.
pub fn default_opset(model: &crate::onnx::proto::ModelProto) -> Option<i64> {
    model.opset_import.iter().find(|o| o.domain.is_empty() || o.domain == "ai.onnx").map(|o| o.version)
}
