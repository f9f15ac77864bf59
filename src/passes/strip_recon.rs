//! `strip-recon`: keep only the detection outputs and what they need.
//!
//! Needs: the image input; a reconstruction output is one frame-sized (or `keep_outputs`
//! names what to keep). A model exported without one keeps every output, with a warning.
//! Guarantees: the kept outputs are computed exactly as before; every node that only served
//! the reconstruction decoder is gone. Reports: outputs removed and kept, nodes removed.

use crate::analysis::partition;
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use anyhow::{bail, Result};

#[derive(serde::Serialize, serde::Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Options {
    /// Outputs to keep, overriding the recognition of the reconstruction output.
    #[serde(default)]
    pub keep_outputs: Option<Vec<String>>,
}

pub struct StripRecon {
    pub options: Options,
}

impl Pass for StripRecon {
    fn name(&self) -> &'static str {
        "strip-recon"
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let keep: Vec<String> = match self.options.keep_outputs.clone().or_else(|| cx.keep_outputs.clone()) {
            Some(k) => k,
            None => {
                let g = model.graph.as_ref().expect("checked by the pipeline");
                let graph = Graph::build(g)?;
                let p = partition::partition(&graph, &infer(&graph));
                if p.recon_outputs.is_empty() {
                    cx.warn(format!(
                        "no output is frame-sized, so the model has no reconstruction output to strip; keeping every output ({}); name them with --keep-outputs to keep fewer",
                        p.det_outputs.join(", ")
                    ));
                }
                p.det_outputs
            }
        };
        let g = super::graph_mut(model)?;
        for k in &keep {
            if !g.output.iter().any(|o| &o.name == k) {
                let names: Vec<&str> = g.output.iter().map(|o| o.name.as_str()).collect();
                bail!("output '{k}' to keep does not exist (outputs: {})", names.join(", "));
            }
        }
        if keep.is_empty() {
            bail!("no detection output left to keep");
        }
        let removed: Vec<String> = g.output.iter().map(|o| o.name.clone()).filter(|o| !keep.contains(o)).collect();
        g.output.retain(|o| keep.contains(&o.name));
        let (nodes, inits, _) = crate::ir::rewrite::dce::eliminate(g)?;
        Ok(serde_json::json!({ "outputs_removed": removed, "outputs_kept": keep, "nodes_removed": nodes, "initializers_removed": inits }))
    }
}
