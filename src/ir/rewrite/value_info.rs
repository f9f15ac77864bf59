//! Inferred types written into a graph's value_info, which ONNX Runtime and tract read.

use crate::ir::{infer, Graph};
use crate::onnx::proto::GraphProto;
use anyhow::Result;
use std::collections::HashSet;

/// Records inferred types in value_info (outputs and inputs excluded); returns how many
/// intermediate values still lack a static shape.
pub fn write_value_info(g: &mut GraphProto) -> Result<usize> {
    let (infos, missing) = {
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        let interface: HashSet<&str> = g.input.iter().chain(&g.output).map(|v| v.name.as_str()).collect();
        let mut infos = Vec::new();
        let mut missing = 0;
        for o in g.node.iter().flat_map(|n| n.output.iter()).filter(|o| !o.is_empty() && !interface.contains(o.as_str())) {
            let t = inf.types.get(o);
            match (t.and_then(|t| t.static_shape()), t.and_then(|t| t.dtype)) {
                (Some(s), Some(dt)) => infos.push(crate::onnx::edit::tensor_value_info(o, dt, &s)),
                _ => missing += 1,
            }
        }
        (infos, missing)
    };
    g.value_info = infos;
    Ok(missing)
}
