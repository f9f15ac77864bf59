//! `dce`: dead code elimination.
//!
//! Needs: a valid graph. Guarantees: every remaining node feeds a graph output; initializers,
//! initializer-shadowing inputs and value_info entries nobody reads are gone. Graph inputs a
//! caller feeds are never removed (that would change the model's interface).
//! Reports: nodes, initializers and value_info entries removed.

use crate::onnx::proto::ModelProto;
use crate::ir::rewrite::dce::eliminate;
use super::{Pass, PassContext};
use anyhow::Result;

pub struct Dce;

impl Pass for Dce {
    fn name(&self) -> &'static str {
        "dce"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let g = super::graph_mut(model)?;
        let (nodes, inits, infos) = eliminate(g)?;
        Ok(serde_json::json!({ "nodes_removed": nodes, "initializers_removed": inits, "value_info_removed": infos }))
    }
}
