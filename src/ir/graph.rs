//! Producers, consumers and topological order over a `GraphProto`, with structural checks.

use crate::onnx::proto::{DimensionValue, GraphProto, NodeProto, TensorProto, TypeValue, ValueInfoProto};
use crate::onnx::tensor_proto::element_count;
use crate::tensor::{onnx_dtype_name, DType};
use anyhow::{bail, Result};
use std::collections::{HashMap, VecDeque};

/// Largest dimension we accept in a declared shape: anything bigger is a corrupt file,
/// not a camera frame (2^31 is also where 32-bit index arithmetic in runtimes breaks).
pub const MAX_DIM: i64 = 1 << 31;

/// Largest element count we accept in a declared value (inputs, outputs, value infos): 2^28
/// (1 GiB of f32), some 90 times a 3-channel 4K frame. A bigger one is a corrupt or hostile
/// file, refused before any frame, feed or output buffer of that size is allocated.
pub const MAX_VALUE_ELEMENTS: i64 = 1 << 28;

pub struct Graph<'m> {
    pub proto: &'m GraphProto,
    /// Value name -> index of the node that produces it.
    pub producer: HashMap<&'m str, usize>,
    /// Value name -> indices of the nodes that read it (once per node).
    pub consumers: HashMap<&'m str, Vec<usize>>,
    pub initializers: HashMap<&'m str, &'m TensorProto>,
    /// Graph inputs that are not initializers: what a caller must feed.
    pub inputs: Vec<&'m ValueInfoProto>,
    /// Node indices in an order where every producer comes before its consumers.
    pub order: Vec<usize>,
}

impl<'m> Graph<'m> {
    /// Indexes `g`, refusing dangling names, double producers, cycles and impossible shapes.
    pub fn build(g: &'m GraphProto) -> Result<Graph<'m>> {
        let initializers: HashMap<&str, &TensorProto> = g.initializer.iter().map(|t| (t.name.as_str(), t)).collect();
        for t in &g.initializer {
            check_initializer(t)?;
        }
        let inputs: Vec<&ValueInfoProto> = g.input.iter().filter(|v| !initializers.contains_key(v.name.as_str())).collect();
        for v in g.input.iter().chain(&g.output).chain(&g.value_info) {
            check_declared_shape(v)?;
        }
        let mut producer: HashMap<&str, usize> = HashMap::new();
        for (i, n) in g.node.iter().enumerate() {
            for o in n.output.iter().filter(|o| !o.is_empty()) {
                if producer.insert(o.as_str(), i).is_some() || initializers.contains_key(o.as_str()) {
                    bail!("value '{o}' is produced more than once (again by {}); each value needs one producer", describe(n));
                }
            }
        }
        let defined = |name: &str| producer.contains_key(name) || initializers.contains_key(name) || g.input.iter().any(|v| v.name == name);
        let mut consumers: HashMap<&str, Vec<usize>> = HashMap::new();
        for (i, n) in g.node.iter().enumerate() {
            for inp in n.input.iter().filter(|s| !s.is_empty()) {
                if !defined(inp) {
                    bail!("dangling value name '{inp}' read by {}: no node, initializer or graph input defines it", describe(n));
                }
                let c = consumers.entry(inp.as_str()).or_default();
                if c.last() != Some(&i) {
                    c.push(i);
                }
            }
        }
        for o in &g.output {
            if !defined(&o.name) {
                bail!("graph output '{}' is never produced", o.name);
            }
        }
        let order = topological_order(g, &producer)?;
        Ok(Graph { proto: g, producer, consumers, initializers, inputs, order })
    }

    pub fn node(&self, i: usize) -> &'m NodeProto {
        &self.proto.node[i]
    }

    /// The node producing `value`, if a node does (not an input or initializer).
    pub fn producer_of(&self, value: &str) -> Option<&'m NodeProto> {
        self.producer.get(value).map(|&i| &self.proto.node[i])
    }

    pub fn consumers_of(&self, value: &str) -> &[usize] {
        self.consumers.get(value).map_or(&[], |v| v.as_slice())
    }

    /// Nodes reachable from the outputs of `from` (not `from` themselves).
    pub fn downstream_of(&self, from: &std::collections::HashSet<usize>) -> std::collections::HashSet<usize> {
        let mut seen = std::collections::HashSet::new();
        let next = |i: usize| self.node(i).output.iter().flat_map(|o| self.consumers_of(o).to_vec()).collect::<Vec<_>>();
        let mut stack: Vec<usize> = from.iter().flat_map(|&i| next(i)).collect();
        while let Some(i) = stack.pop() {
            if seen.insert(i) {
                stack.extend(next(i));
            }
        }
        seen
    }

    /// Which nodes `values` depend on (their backward cone), by node index.
    pub fn cone(&self, values: impl IntoIterator<Item = &'m str>) -> Vec<bool> {
        let mut seen = vec![false; self.proto.node.len()];
        let mut stack: Vec<&str> = values.into_iter().collect();
        while let Some(v) = stack.pop() {
            if let Some(&i) = self.producer.get(v) {
                if !seen[i] {
                    seen[i] = true;
                    stack.extend(self.proto.node[i].input.iter().filter(|s| !s.is_empty()).map(|s| s.as_str()));
                }
            }
        }
        seen
    }
}

pub fn describe(n: &NodeProto) -> String {
    if n.name.is_empty() {
        format!("a {} node", n.op_type)
    } else {
        format!("node '{}' ({})", n.name, n.op_type)
    }
}

fn topological_order(g: &GraphProto, producer: &HashMap<&str, usize>) -> Result<Vec<usize>> {
    let n = g.node.len();
    let mut indegree = vec![0usize; n];
    let mut users: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (i, node) in g.node.iter().enumerate() {
        for inp in node.input.iter().filter(|s| !s.is_empty()) {
            if let Some(&p) = producer.get(inp.as_str()) {
                indegree[i] += 1;
                users[p].push(i);
            }
        }
    }
    let mut ready: VecDeque<usize> = (0..n).filter(|&i| indegree[i] == 0).collect();
    let mut order = Vec::with_capacity(n);
    while let Some(i) = ready.pop_front() {
        order.push(i);
        for &u in &users[i] {
            indegree[u] -= 1;
            if indegree[u] == 0 {
                ready.push_back(u);
            }
        }
    }
    if order.len() < n {
        let stuck = (0..n).find(|&i| indegree[i] > 0).expect("some node is left");
        bail!("the graph has a cycle through {}; ONNX graphs must be acyclic", describe(&g.node[stuck]));
    }
    Ok(order)
}

fn check_declared_shape(v: &ValueInfoProto) -> Result<()> {
    let Some(TypeValue::TensorType(t)) = v.r#type.as_ref().and_then(|t| t.value.as_ref()) else { return Ok(()) };
    for d in t.shape.iter().flat_map(|s| &s.dim) {
        if let Some(DimensionValue::DimValue(x)) = d.value {
            if x < 0 {
                bail!("value '{}' declares a negative dimension ({x})", v.name);
            }
            if x > MAX_DIM {
                bail!("value '{}' declares an absurd dimension ({x} > 2^31): corrupt file?", v.name);
            }
        }
    }
    let dims: Vec<i64> = t.shape.iter().flat_map(|s| &s.dim).filter_map(|d| match d.value {
        Some(DimensionValue::DimValue(x)) => Some(x),
        _ => None,
    }).collect();
    // Saturating: 2^30 x 2^30 must not wrap around into a small count.
    let n = dims.iter().fold(1i64, |a, &x| a.saturating_mul(x));
    if n > MAX_VALUE_ELEMENTS {
        bail!("value '{}' declares {dims:?}, over {MAX_VALUE_ELEMENTS} elements (1 GiB of f32): corrupt file?", v.name);
    }
    Ok(())
}

/// Checks an initializer's claimed shape against the data it really stores, without copying it.
fn check_initializer(t: &TensorProto) -> Result<()> {
    let n = element_count(&t.dims).map_err(|e| anyhow::anyhow!("initializer '{}': {e}", t.name))?;
    if t.dims.iter().any(|&d| d > MAX_DIM) {
        bail!("initializer '{}' declares an absurd dimension in {:?}: corrupt file?", t.name, t.dims);
    }
    let Some(dt) = DType::from_onnx(t.data_type) else { return Ok(()) }; // exotic types: left to the runtime
    let stored = if !t.raw_data.is_empty() {
        if dt == DType::Str { 0 } else { t.raw_data.len() / dt.size_of().max(1) }
    } else {
        match dt {
            DType::F32 => t.float_data.len(),
            DType::F64 => t.double_data.len(),
            DType::I64 => t.int64_data.len(),
            DType::U32 | DType::U64 => t.uint64_data.len(),
            DType::Str => t.string_data.len(),
            _ => t.int32_data.len(),
        }
    };
    let raw_ok = t.raw_data.is_empty() || dt == DType::Str || t.raw_data.len().is_multiple_of(dt.size_of());
    if stored != n || !raw_ok {
        bail!("initializer '{}' ({}) claims shape {:?} ({n} values) but stores {stored}", t.name, onnx_dtype_name(t.data_type), t.dims);
    }
    Ok(())
}
