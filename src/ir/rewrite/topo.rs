//! Node order: producers before consumers, which ONNX requires and edits that append nodes
//! break.

use crate::onnx::proto::{GraphProto, NodeProto};

/// Reorders nodes so producers come first (ONNX requires it; edits may append nodes).
pub fn sort_topologically(g: &mut GraphProto) -> anyhow::Result<()> {
    let order = crate::ir::Graph::build(g)?.order;
    let mut nodes: Vec<Option<NodeProto>> = std::mem::take(&mut g.node).into_iter().map(Some).collect();
    g.node = order.into_iter().map(|i| nodes[i].take().expect("each index once")).collect();
    Ok(())
}
