//! The QOperator form of a QDQ graph for tract: DQ -> Conv -> Q becomes one QLinearConv on
//! the integer tensors (per-channel weight scales as QLinearConv's w_scale vector, int32
//! bias). tract runs QDQ Conv in float and reads only the first element of a per-axis
//! DequantizeLinear scale, while QLinearConv goes through its quantized convolution with the
//! whole scale vector. Everything else keeps its Q/DQ pairs.

use crate::ir::Graph;
use crate::onnx::attr;
use crate::onnx::edit::remove_nodes;
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::{GraphProto, NodeProto};
use anyhow::Result;
use std::collections::HashSet;

/// Rewrites every fusable convolution of `g`; returns how many.
pub fn to_qlinear_conv(g: &mut GraphProto) -> Result<usize> {
    let rewrites: Vec<(usize, usize, NodeProto)> = {
        let graph = Graph::build(g)?;
        let dq = |v: &str| graph.producer_of(v).filter(|n| n.op_type == "DequantizeLinear" && n.input.len() == 3);
        let mut out = Vec::new();
        for &i in &graph.order {
            let conv = graph.node(i);
            if conv.op_type != "Conv" {
                continue;
            }
            let (Some(x), Some(w)) = (dq(&conv.input[0]), conv.input.get(1).and_then(|v| dq(v))) else { continue };
            // Weights per output channel (axis 0); the activation's scale is a scalar.
            if attr::int(w, "axis", 1) != 0 {
                continue;
            }
            let bias = match conv.input.get(2).filter(|b| !b.is_empty()) {
                Some(b) => match dq(b) {
                    Some(d) => Some(d.input[0].clone()),
                    None => continue,
                },
                None => None,
            };
            let readers = graph.consumers_of(&conv.output[0]);
            let is_output = g.output.iter().any(|o| o.name == conv.output[0]);
            let [q] = readers else { continue };
            let qn = graph.node(*q);
            if is_output || qn.op_type != "QuantizeLinear" || qn.input.len() != 3 {
                continue;
            }
            let mut input = vec![x.input[0].clone(), x.input[1].clone(), x.input[2].clone(), w.input[0].clone(), w.input[1].clone(), w.input[2].clone(), qn.input[1].clone(), qn.input[2].clone()];
            input.extend(bias);
            let attribute = conv.attribute.clone();
            out.push((i, *q, NodeProto { op_type: "QLinearConv".into(), name: format!("{}_qlinear", conv.name), input, output: qn.output.clone(), attribute, ..Default::default() }));
        }
        out
    };
    let count = rewrites.len();
    let mut dead = HashSet::new();
    for (conv, q, fused) in rewrites {
        g.node[conv] = fused;
        dead.insert(q);
    }
    remove_nodes(g, &dead);
    sort_topologically(g)?;
    crate::ir::rewrite::dce::eliminate(g)?;
    Ok(count)
}
