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
