//! Dead code elimination: what no graph output needs goes.

use crate::ir::Graph;
use crate::onnx::proto::GraphProto;
use anyhow::Result;
use std::collections::HashSet;

/// Removes what no graph output needs; returns (nodes, initializers, value_info) removed.
pub fn eliminate(g: &mut GraphProto) -> Result<(usize, usize, usize)> {
    let dead: HashSet<usize> = {
        let graph = Graph::build(g)?;
        let live = graph.cone(g.output.iter().map(|o| o.name.as_str()));
        live.iter().enumerate().filter(|(_, &l)| !l).map(|(i, _)| i).collect()
    };
    crate::onnx::edit::remove_nodes(g, &dead);
    let mut used: HashSet<String> = g.node.iter().flat_map(|n| n.input.iter().cloned()).collect();
    used.extend(g.output.iter().map(|o| o.name.clone()));
    // Subgraphs (If/Loop bodies) may read outer values by name without listing them as inputs.
    for n in &g.node {
        for a in &n.attribute {
            for sg in a.g.iter().chain(&a.graphs) {
                used.extend(sg.node.iter().flat_map(|n| n.input.iter().cloned()));
            }
        }
    }
    let removed: HashSet<String> = g.initializer.iter().filter(|t| !used.contains(&t.name)).map(|t| t.name.clone()).collect();
    g.initializer.retain(|t| !removed.contains(&t.name));
    // Old-style models also list initializers as inputs: such an entry goes with its initializer.
    g.input.retain(|v| !removed.contains(&v.name));
    let mut known: HashSet<String> = g.node.iter().flat_map(|n| n.output.iter().cloned()).collect();
    known.extend(g.initializer.iter().map(|t| t.name.clone()));
    let before = g.value_info.len();
    g.value_info.retain(|v| known.contains(&v.name));
    Ok((dead.len(), removed.len(), before - g.value_info.len()))
}
