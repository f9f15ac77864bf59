//! `cleanup`: Identity and Dropout (inference no-ops) bypassed, duplicate initializers merged.
//!
//! Needs: a valid graph. Guarantees: same outputs, bit for bit; graph output names kept.
//! Reports: no-ops removed, initializers merged.

use crate::onnx::edit::{remove_nodes, replace_value};
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use anyhow::Result;
use sha2::{Digest, Sha256};
use std::collections::{HashMap, HashSet};

pub struct Cleanup;

impl Pass for Cleanup {
    fn name(&self) -> &'static str {
        "cleanup"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let g = super::graph_mut(model)?;
        let mut bypassed = HashSet::new();
        for i in 0..g.node.len() {
            let n = &g.node[i];
            // Dropout's optional mask output is a real value; only the plain form is a no-op.
            let noop = n.op_type == "Identity" || (n.op_type == "Dropout" && n.output.iter().skip(1).all(|o| o.is_empty()));
            if !noop || !n.domain.is_empty() || n.input.is_empty() {
                continue;
            }
            let (from, to) = (n.output[0].clone(), n.input[0].clone());
            if replace_value(g, &from, &to) {
                bypassed.insert(i);
            }
        }
        remove_nodes(g, &bypassed);

        // Same dtype, dims and bytes: one initializer serves all readers.
        let mut seen: HashMap<[u8; 32], String> = HashMap::new();
        let mut alias: HashMap<String, String> = HashMap::new();
        let outputs: HashSet<&str> = g.output.iter().map(|o| o.name.as_str()).collect();
        for t in &g.initializer {
            if t.raw_data.is_empty() || outputs.contains(t.name.as_str()) || g.input.iter().any(|v| v.name == t.name) {
                continue;
            }
            let mut h = Sha256::new();
            h.update(t.data_type.to_le_bytes());
            for d in &t.dims {
                h.update(d.to_le_bytes());
            }
            h.update(&t.raw_data);
            match seen.entry(h.finalize().into()) {
                std::collections::hash_map::Entry::Occupied(e) => {
                    alias.insert(t.name.clone(), e.get().clone());
                }
                std::collections::hash_map::Entry::Vacant(e) => {
                    e.insert(t.name.clone());
                }
            }
        }
        for n in &mut g.node {
            for i in n.input.iter_mut() {
                if let Some(a) = alias.get(i) {
                    *i = a.clone();
                }
            }
        }
        g.initializer.retain(|t| !alias.contains_key(&t.name));
        Ok(serde_json::json!({ "noops_removed": bypassed.len(), "initializers_merged": alias.len() }))
    }
}
