//! Where tract loses to ONNX Runtime on one model: the two engines' layers joined by the model
//! node each ran, the difference per layer and per kind of tract kernel, and the time in
//! kernels the other engine has no counterpart for (ORT's layout reorders and the activations
//! it fused, tract's own reshapes). The profile's map for what only tract's kernels can fix.

use super::op_profile::OpProfile;
use serde::Serialize;
use std::collections::HashMap;

/// Layers listed, largest loss first.
const TOP: usize = 8;

#[derive(Clone, Debug, Serialize)]
pub struct EngineGap {
    pub ort_kernel_ms: f64,
    pub tract_kernel_ms: f64,
    /// The layers both ran, by tract's kernel for them, largest loss first.
    pub by_tract_op: Vec<OpGap>,
    /// The layers where tract spends the most beyond ONNX Runtime.
    pub layers: Vec<LayerGap>,
    /// Kernels that match no layer of the other engine.
    pub ort_only_ms: f64,
    pub tract_only_ms: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct OpGap {
    pub op: String,
    pub layers: usize,
    pub tract_ms: f64,
    pub ort_ms: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct LayerGap {
    pub node: String,
    pub tract_op: String,
    pub ort_op: String,
    pub tract_ms: f64,
    pub ort_ms: f64,
    pub macs: u64,
}

/// The gap between `ort`'s and `tract`'s profiles of the same model.
pub fn between(ort: &OpProfile, tract: &OpProfile) -> EngineGap {
    let theirs: HashMap<&str, &super::op_profile::LayerTime> = ort.all_layers.iter().map(|l| (l.node.as_str(), l)).collect();
    let mut by_op: Vec<OpGap> = Vec::new();
    let mut layers = Vec::new();
    let mut matched = std::collections::HashSet::new();
    let mut tract_only_ms = 0.0;
    for l in &tract.all_layers {
        let Some(o) = theirs.get(l.node.as_str()) else {
            tract_only_ms += l.ms;
            continue;
        };
        matched.insert(o.node.as_str());
        let op = first_op(&l.op).to_string();
        match by_op.iter_mut().find(|g| g.op == op) {
            Some(g) => {
                g.layers += 1;
                g.tract_ms += l.ms;
                g.ort_ms += o.ms;
            }
            None => by_op.push(OpGap { op, layers: 1, tract_ms: l.ms, ort_ms: o.ms }),
        }
        layers.push(LayerGap { node: l.node.clone(), tract_op: l.op.clone(), ort_op: o.op.clone(), tract_ms: l.ms, ort_ms: o.ms, macs: l.macs });
    }
    let ort_only_ms = ort.all_layers.iter().filter(|l| !matched.contains(l.node.as_str())).map(|l| l.ms).sum();
    let loss = |t: f64, o: f64| t - o;
    by_op.sort_by(|a, b| loss(b.tract_ms, b.ort_ms).total_cmp(&loss(a.tract_ms, a.ort_ms)));
    layers.sort_by(|a, b| loss(b.tract_ms, b.ort_ms).total_cmp(&loss(a.tract_ms, a.ort_ms)));
    layers.truncate(TOP);
    EngineGap { ort_kernel_ms: ort.kernel_ms, tract_kernel_ms: tract.kernel_ms, by_tract_op: by_op, layers, ort_only_ms, tract_only_ms }
}

/// The kernel that did a layer's work, first of the `+`-joined kernels tract ran for it (the
/// bias add and the like come after); a `+` inside a kernel's own parentheses is its own.
fn first_op(ops: &str) -> &str {
    let mut depth = 0i32;
    for (i, c) in ops.char_indices() {
        match c {
            '(' => depth += 1,
            ')' => depth -= 1,
            '+' if depth == 0 => return &ops[..i],
            _ => {}
        }
    }
    ops
}

impl EngineGap {
    /// A few lines: the kernels' totals, the kinds of layer tract loses on, the worst layers.
    pub fn render(&self) -> String {
        let mut s = format!(
            "tract against ONNX Runtime: kernels {:.2} ms against {:.2} ms; in kernels the other engine has no layer for, tract {:.2} ms, ONNX Runtime {:.2} ms\n",
            self.tract_kernel_ms, self.ort_kernel_ms, self.tract_only_ms, self.ort_only_ms
        );
        s += "  layers run by tract as          layers   tract ms     ORT ms   tract - ORT\n";
        for g in &self.by_tract_op {
            s += &format!("  {:<30} {:>7} {:>10.2} {:>10.2} {:>+13.2}\n", g.op, g.layers, g.tract_ms, g.ort_ms, g.tract_ms - g.ort_ms);
        }
        s += "  layers it loses most on\n";
        for l in &self.layers {
            s += &format!("  {:<46} {:>7.2} {:>7.2} ms  {} / {}\n", l.node, l.tract_ms, l.ort_ms, l.tract_op, l.ort_op);
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::runtime::op_profile::LayerTime;
    use crate::runtime::Engine;

    fn profile(engine: Engine, layers: &[(&str, &str, f64)]) -> OpProfile {
        let all_layers: Vec<LayerTime> = layers.iter().map(|(n, op, ms)| LayerTime { node: n.to_string(), op: op.to_string(), ms: *ms, macs: 0, bytes: 0, gmacs_per_s: None, gbytes_per_s: 0.0 }).collect();
        OpProfile { engine, run_ms: 0.0, kernel_ms: layers.iter().map(|l| l.2).sum(), kernels: layers.len(), by_op: vec![], layers: vec![], macs: 0, gmacs_per_s: 0.0, best_gmacs_per_s: 0.0, all_layers }
    }

    #[test]
    fn layers_join_by_node_and_the_rest_counts_apart() {
        let ort = profile(Engine::Ort, &[("/a/Conv", "Conv", 1.0), ("/b/Conv", "Conv", 2.0), ("/dw/Conv", "Conv", 0.5), ("ReorderOutput", "ReorderOutput", 0.7)]);
        let tract = profile(Engine::Tract, &[("/a/Conv", "DirectSpatialConv+OptAddUnicast", 3.0), ("/b/Conv", "OptMatMul", 1.5), ("/dw/Conv", "DepthWiseConv", 2.5), ("/x/Reshape", "Reshape", 0.2)]);
        let g = between(&ort, &tract);
        assert_eq!((g.tract_kernel_ms, g.ort_kernel_ms), (7.2, 4.2));
        assert!((g.tract_only_ms - 0.2).abs() < 1e-12 && (g.ort_only_ms - 0.7).abs() < 1e-12, "{g:?}");
        let ops: Vec<(&str, f64)> = g.by_tract_op.iter().map(|o| (o.op.as_str(), o.tract_ms - o.ort_ms)).collect();
        assert_eq!(ops, vec![("DirectSpatialConv", 2.0), ("DepthWiseConv", 2.0), ("OptMatMul", -0.5)]);
        assert_eq!(g.layers[2].node, "/b/Conv", "the layer tract wins on comes last");
        assert_eq!(first_op("OptBinChain(Mul+Add)+Cast"), "OptBinChain(Mul+Add)");
    }
}
