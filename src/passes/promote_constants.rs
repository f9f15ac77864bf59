//! `promote-constants`: Constant nodes holding tensors become initializers.
//!
//! Paddle's and tf2onnx's exporters write weights as Constant nodes; the passes that read
//! weights (BN folding, pruning, quantization, FP16) look for initializers. Promoting them
//! first lets every later pass see the model as PyTorch would have written it.
//! Needs: nothing. Guarantees: every value computed as before (the same tensors, now read from
//! the initializer list); a Constant whose output is a graph output, or whose name an
//! initializer or graph input already holds, stays a node. Reports: nodes promoted, elements.

use crate::onnx::attr;
use crate::onnx::proto::{GraphProto, ModelProto};
use super::{Pass, PassContext};
use anyhow::Result;
use std::collections::HashSet;

pub struct PromoteConstants;

impl Pass for PromoteConstants {
    fn name(&self) -> &'static str {
        "promote-constants"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        if model.ir_version < 4 {
            // Before IR 4 every initializer must also be listed as a graph input.
            return Ok(serde_json::json!({ "constants_promoted": 0, "skipped": "IR version below 4" }));
        }
        let (nodes, elements) = promote(super::graph_mut(model)?);
        Ok(serde_json::json!({ "constants_promoted": nodes, "elements": elements }))
    }
}

/// Moves the promotable Constant nodes of `g` into its initializers; returns (nodes, elements).
pub fn promote(g: &mut GraphProto) -> (usize, u64) {
    let taken: HashSet<String> = g.initializer.iter().map(|t| t.name.clone()).chain(g.input.iter().map(|v| v.name.clone())).chain(g.output.iter().map(|v| v.name.clone())).collect();
    let (mut nodes, mut elements) = (0, 0u64);
    let mut kept = Vec::with_capacity(g.node.len());
    for n in std::mem::take(&mut g.node) {
        let promotable = n.op_type == "Constant" && n.domain.is_empty() && n.output.len() == 1 && !taken.contains(&n.output[0]);
        match attr::tensor(&n, "value").filter(|_| promotable) {
            Some(t) => {
                let mut t = t.clone();
                t.name = n.output[0].clone();
                elements += t.dims.iter().map(|&d| d.max(0) as u64).product::<u64>();
                g.initializer.push(t);
                nodes += 1;
            }
            None => kept.push(n),
        }
    }
    g.node = kept;
    (nodes, elements)
}
