//! Where a run's time goes, per operator type and per layer, on ONNX Runtime and on tract:
//! the map for making latency follow the MACs.
//!
//! Each layer's time is set beside what it computes and moves: its MACs ([`cost::macs`]) and
//! the bytes of the activations it reads and writes (weights left out), both from the
//! model's inferred shapes. A narrow convolution over a 640x480 map does few MACs and moves
//! many bytes; its GMAC/s says how far it is from what the engine reaches on this CPU, which
//! is the best any of the model's own layers achieves ([`OpProfile::best_gmacs_per_s`]).
//!
//! ORT renames what it runs: a fused QDQ convolution keeps the Conv's name (its layout pass
//! appends `_token_<n>`, undone by [`super::ort_profile::KernelTime::source`]); an NCHWc
//! convolution is named after its output value with `_nchwc` appended, and that value may be
//! the output of an activation ORT fused into it; a Conv fused with its BatchNormalization and
//! activation may carry the name of either follower. tract appends suffixes to the names it
//! keeps (`.conv`, `.bias`, `#0`). Each is traced back to the model's node; what matches none
//! (a reorder ORT inserted, a tract reshape) keeps its own name and counts under its op.

use super::ort_profile;
use super::Engine;
use crate::ir::{cost, graph::Graph, shapes::{infer, Inferred}};
use crate::onnx::proto::ModelProto;
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};
use serde::Serialize;
use std::collections::HashMap;
use std::time::Instant;

/// Layers listed, slowest first.
const TOP_LAYERS: usize = 12;
/// tract runs per-node timed; the first ones are left out of the medians.
const TRACT_RUNS: usize = 7;
const TRACT_WARMUP: usize = 2;

#[derive(Clone, Debug, Serialize)]
pub struct OpProfile {
    pub engine: Engine,
    /// Median whole run, as the engine's profile timed it.
    pub run_ms: f64,
    /// Sum of the per-kernel medians (the rest of `run_ms` is the engine's own overhead).
    pub kernel_ms: f64,
    pub kernels: usize,
    pub by_op: Vec<OpShare>,
    pub layers: Vec<LayerTime>,
    pub macs: u64,
    /// The model's MACs over the whole run's time.
    pub gmacs_per_s: f64,
    /// The fastest GMAC/s any layer of 1 M MACs or more reached: what this engine does on this
    /// CPU when a layer suits it.
    pub best_gmacs_per_s: f64,
    /// Every layer, slowest first (`layers` keeps the first few): what `engine_gap` joins
    /// across engines.
    #[serde(skip)]
    pub all_layers: Vec<LayerTime>,
}

#[derive(Clone, Debug, Serialize)]
pub struct OpShare {
    pub op: String,
    pub kernels: usize,
    pub ms: f64,
    /// Of the kernels' summed time.
    pub share: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct LayerTime {
    /// The model's node (or the engine's own, when it matches none).
    pub node: String,
    /// What the engine ran for it.
    pub op: String,
    pub ms: f64,
    pub macs: u64,
    /// Activation bytes read and written.
    pub bytes: u64,
    pub gmacs_per_s: Option<f64>,
    pub gbytes_per_s: f64,
}

impl OpProfile {
    /// A screen: the run, the operator types, the slowest layers.
    pub fn render(&self) -> String {
        let engine = match self.engine {
            Engine::Ort => "ONNX Runtime",
            Engine::Tract => "tract",
        };
        let mut s = format!(
            "{engine}: run {:.2} ms ({:.2} ms in {} kernels), {:.0} M MACs at {:.1} GMAC/s; the best layer reached {:.1} GMAC/s\n\n",
            self.run_ms, self.kernel_ms, self.kernels, self.macs as f64 / 1e6, self.gmacs_per_s, self.best_gmacs_per_s
        );
        s += "  operator                     kernels       ms   share\n";
        for o in self.by_op.iter().take(10) {
            s += &format!("  {:<28} {:>7} {:>8.2} {:>6.1}%\n", o.op, o.kernels, o.ms, o.share * 100.0);
        }
        s += "\n  slowest layers                                    ms    M MACs  GMAC/s   MB moved   GB/s  ran as\n";
        for l in &self.layers {
            let g = l.gmacs_per_s.map_or("-".into(), |g| format!("{g:.1}"));
            s += &format!("  {:<46} {:>6.2} {:>8.1} {:>7} {:>9.1} {:>6.1}  {}\n", l.node, l.ms, l.macs as f64 / 1e6, g, l.bytes as f64 / 1e6, l.gbytes_per_s, l.op);
        }
        s
    }
}

/// Profiles `model` on `engine` with `threads` threads on `inputs`.
pub fn profile(engine: Engine, model: &ModelProto, inputs: &[(String, Tensor)], threads: usize) -> Result<OpProfile> {
    let (run_ms, kernels) = match engine {
        Engine::Ort => {
            let p = ort_profile::profile(model, inputs, threads)?;
            (p.run_ms, p.kernels.iter().map(|k| (k.source().to_string(), k.op.clone(), k.ms)).collect())
        }
        Engine::Tract => tract_kernels(model, inputs, threads)?,
    };
    let graph = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let g = Graph::build(graph)?;
    Ok(summarize(engine, run_ms, kernels, &Costs::of(&g, &infer(&g))))
}

/// Per node of the model: MACs and activation bytes, and how engine names lead to it.
struct Costs {
    by_node: HashMap<String, (u64, u64)>,
    /// Value name -> the node whose cost it stands for (the convolution under a fused activation).
    by_value: HashMap<String, String>,
    /// A normalization or activation that ONNX Runtime fuses into the convolution before it ->
    /// that convolution: the fused kernel may carry the follower's name (Conv, BN, Relu runs
    /// as one Conv kernel named after the Relu).
    fused: HashMap<String, String>,
}

impl Costs {
    fn of(g: &Graph, inf: &Inferred) -> Costs {
        let bytes_of = |v: &str| -> u64 {
            if g.initializers.contains_key(v) {
                return 0;
            }
            let t = inf.types.get(v);
            let elems: u64 = t.and_then(|t| t.static_shape()).map_or(0, |s| s.iter().map(|&d| d as u64).product());
            elems * t.and_then(|t| t.dtype).map_or(4, |d| d.size_of() as u64)
        };
        let mut by_node = HashMap::new();
        let mut by_value = HashMap::new();
        let mut fused = HashMap::new();
        for &i in &g.order {
            let n = g.node(i);
            let moved: u64 = n.input.iter().chain(&n.output).filter(|v| !v.is_empty()).map(|v| bytes_of(v)).sum();
            by_node.insert(n.name.clone(), (cost::macs(n, inf), moved));
            // A normalization or activation stands for the convolution ORT fuses it into,
            // when it is the only reader of that convolution (or of its normalization).
            let conv = g
                .producer_of(n.input.first().map_or("", |s| s.as_str()))
                .filter(|p| matches!(n.op_type.as_str(), "BatchNormalization" | "Relu" | "Sigmoid" | "Clip" | "LeakyRelu" | "HardSigmoid" | "Tanh") && g.consumers_of(&p.output[0]).len() == 1)
                .map(|p| by_value.get(&p.output[0]).cloned().unwrap_or_else(|| p.name.clone()))
                .filter(|c| by_node.get(c).is_some_and(|c: &(u64, u64)| c.0 > 0));
            if let Some(c) = &conv {
                fused.insert(n.name.clone(), c.clone());
            }
            let source = conv.unwrap_or_else(|| n.name.clone());
            for o in &n.output {
                by_value.insert(o.clone(), source.clone());
            }
        }
        Costs { by_node, by_value, fused }
    }

    /// The model node an engine's kernel name stands for.
    fn node_of(&self, name: &str) -> Option<&str> {
        let known = |n: &str| self.by_node.get_key_value(unsplit(n)).map(|(k, _)| self.fused.get(k).map_or(k.as_str(), |c| c.as_str()));
        if let Some(k) = known(name) {
            return Some(k);
        }
        if let Some(v) = name.strip_suffix("_nchwc") {
            return self.by_value.get(v).map(|s| s.as_str());
        }
        // tract: the longest model name that the kernel's name extends at a '.' or '#'.
        let mut end = name.len();
        while let Some(cut) = name[..end].rfind(['.', '#']) {
            if let Some(k) = known(&name[..cut]) {
                return Some(k);
            }
            end = cut;
        }
        None
    }
}

/// A wide depthwise convolution's name before tract's preparation split it into bands and
/// their sums (`split-wide-depthwise`: `<name>_band<i>`, `<name>_sum<i>`).
fn unsplit(name: &str) -> &str {
    for tag in ["_band", "_sum"] {
        if let Some(at) = name.rfind(tag) {
            let n = &name[at + tag.len()..];
            if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()) {
                return &name[..at];
            }
        }
    }
    name
}

fn summarize(engine: Engine, run_ms: f64, kernels: Vec<(String, String, f64)>, costs: &Costs) -> OpProfile {
    let kernel_ms: f64 = kernels.iter().map(|k| k.2).sum();
    let mut by_op: Vec<OpShare> = Vec::new();
    for (_, op, ms) in &kernels {
        match by_op.iter_mut().find(|s| &s.op == op) {
            Some(s) => {
                s.kernels += 1;
                s.ms += ms;
            }
            None => by_op.push(OpShare { op: op.clone(), kernels: 1, ms: *ms, share: 0.0 }),
        }
    }
    for s in &mut by_op {
        s.share = s.ms / kernel_ms.max(f64::MIN_POSITIVE);
    }
    by_op.sort_by(|a, b| b.ms.total_cmp(&a.ms));
    // Kernels of one model node (tract splits a convolution into several) add up.
    let mut layers: Vec<LayerTime> = Vec::new();
    for (name, op, ms) in &kernels {
        let node = costs.node_of(name).unwrap_or(name);
        match layers.iter_mut().find(|l| l.node == node) {
            Some(l) => {
                l.ms += ms;
                if !l.op.split('+').any(|o| o == op) {
                    l.op = format!("{}+{op}", l.op);
                }
            }
            None => {
                let (macs, bytes) = costs.by_node.get(node).copied().unwrap_or((0, 0));
                layers.push(LayerTime { node: node.to_string(), op: op.clone(), ms: *ms, macs, bytes, gmacs_per_s: None, gbytes_per_s: 0.0 });
            }
        }
    }
    for l in &mut layers {
        let s = l.ms.max(1e-6) / 1e3;
        l.gmacs_per_s = (l.macs > 0).then(|| l.macs as f64 / s / 1e9);
        l.gbytes_per_s = l.bytes as f64 / s / 1e9;
    }
    let macs: u64 = costs.by_node.values().map(|c| c.0).sum();
    let best = layers.iter().filter(|l| l.macs >= 1_000_000).filter_map(|l| l.gmacs_per_s).fold(0.0, f64::max);
    layers.sort_by(|a, b| b.ms.total_cmp(&a.ms));
    let all_layers = layers.clone();
    layers.truncate(TOP_LAYERS);
    OpProfile {
        engine,
        run_ms,
        kernel_ms,
        kernels: kernels.len(),
        by_op,
        layers,
        macs,
        gmacs_per_s: macs as f64 / (run_ms.max(1e-6) / 1e3) / 1e9,
        best_gmacs_per_s: best,
        all_layers,
    }
}

/// tract's plan run node by node with each node's evaluation timed: (node name, op, median ms).
fn tract_kernels(model: &ModelProto, inputs: &[(String, Tensor)], threads: usize) -> Result<(f64, Vec<(String, String, f64)>)> {
    use tract_onnx::tract_core::plan::eval;
    let rt = super::tract_runtime::TractRuntime::new(model, inputs, threads)?;
    let plan = rt.plan();
    let nodes = plan.model().nodes();
    let mut per: Vec<Vec<f64>> = vec![Vec::new(); nodes.len()];
    let mut runs = Vec::new();
    for run in 0..TRACT_RUNS {
        let values = rt.input_values(inputs)?;
        let mut state = plan.spawn().map_err(|e| anyhow!("tract: {e:#}"))?;
        let mut times = vec![0.0; nodes.len()];
        let t = Instant::now();
        state
            .run_plan_with_eval(values, |ctx, st, node, input| {
                let t = Instant::now();
                let r = eval(ctx, st, node, input);
                times[node.id] += t.elapsed().as_secs_f64() * 1e3;
                r
            })
            .map_err(|e| anyhow!("tract failed: {e:#}"))?;
        if run >= TRACT_WARMUP {
            runs.push(t.elapsed().as_secs_f64() * 1e3);
            for (p, t) in per.iter_mut().zip(times) {
                p.push(t);
            }
        }
    }
    let order = plan.order_without_consts();
    let kernels = order
        .iter()
        .map(|&i| (nodes[i].name.clone(), nodes[i].op().name().to_string(), crate::metrics::order::median(per[i].clone())))
        .filter(|k| k.2 > 0.0)
        .collect();
    Ok((crate::metrics::order::median(runs), kernels))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn costs() -> Costs {
        let by_node = [("/a/Conv", (1000, 10)), ("/a/Relu", (0, 8)), ("/b/body.0/Conv", (500, 4))].into_iter().map(|(k, v)| (k.to_string(), v)).collect();
        let pairs = |p: &[(&str, &str)]| p.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        let by_value = pairs(&[("/a/Relu_output_0", "/a/Conv"), ("/a/Conv_output_0", "/a/Conv")]);
        Costs { by_node, by_value, fused: pairs(&[("/a/Relu", "/a/Conv")]) }
    }

    #[test]
    fn engine_names_lead_to_model_nodes() {
        let c = costs();
        assert_eq!(c.node_of("/a/Conv"), Some("/a/Conv"));
        assert_eq!(c.node_of("/a/Relu"), Some("/a/Conv"), "a fused kernel named after its activation");
        assert_eq!(c.node_of("/a/Relu_output_0_nchwc"), Some("/a/Conv"), "an NCHWc convolution named after its fused activation's output");
        assert_eq!(c.node_of("/b/body.0/Conv.conv#1"), Some("/b/body.0/Conv"), "tract's suffixes");
        assert_eq!(c.node_of("/b/body.0/Conv.bias"), Some("/b/body.0/Conv"));
        assert_eq!(c.node_of("/a/Conv_band1"), Some("/a/Conv"), "a band of a split depthwise convolution");
        assert_eq!(c.node_of("/a/Conv_sum0.add"), Some("/a/Conv"));
        assert_eq!(c.node_of("/a/Conv_bandx"), None);
        assert_eq!(c.node_of("ReorderOutput_3"), None);
        assert_eq!(c.node_of("/b/body"), None, "a prefix of a name is not the node");
    }

    /// Conv, BatchNormalization, Relu runs as one ORT kernel named after the BN or the Relu;
    /// a SiLU's Sigmoid shares the convolution's output with its Mul and is not fused.
    #[test]
    fn a_convolutions_fused_followers_stand_for_it() {
        use crate::onnx::{edit::{add_constant, tensor_value_info}, proto::{GraphProto, NodeProto}};
        use crate::tensor::DType;
        let node = |name: &str, op: &str, i: &[&str], o: &str| NodeProto { name: name.into(), op_type: op.into(), input: i.iter().map(|s| s.to_string()).collect(), output: vec![o.into()], ..Default::default() };
        let mut g = GraphProto { input: vec![tensor_value_info("x", DType::F32, &[1, 2, 4, 4])], output: vec![tensor_value_info("y", DType::F32, &[1, 2, 4, 4]), tensor_value_info("z", DType::F32, &[1, 2, 4, 4])], ..Default::default() };
        let w = add_constant(&mut g, "w", &Tensor::f32(vec![2, 2, 1, 1], vec![1.0; 4]));
        let v = add_constant(&mut g, "v", &Tensor::f32(vec![2], vec![1.0; 2]));
        g.node = vec![
            node("conv", "Conv", &["x", &w], "c"),
            node("bn", "BatchNormalization", &["c", &v, &v, &v, &v], "b"),
            node("relu", "Relu", &["b"], "y"),
            node("conv2", "Conv", &["y", &w], "c2"),
            node("sig", "Sigmoid", &["c2"], "s"),
            node("mul", "Mul", &["c2", "s"], "z"),
        ];
        let graph = Graph::build(&g).unwrap();
        let c = Costs::of(&graph, &infer(&graph));
        assert_eq!((c.node_of("relu"), c.node_of("bn"), c.node_of("conv")), (Some("conv"), Some("conv"), Some("conv")));
        assert_eq!(c.node_of("y_nchwc"), Some("conv"));
        assert_eq!((c.node_of("sig"), c.node_of("mul")), (Some("sig"), Some("mul")));
    }

    #[test]
    fn layers_add_their_kernels_and_ops_share_the_kernel_time() {
        let k = |n: &str, op: &str, ms: f64| (n.to_string(), op.to_string(), ms);
        let p = summarize(Engine::Tract, 4.0, vec![k("/a/Conv.conv", "Conv", 1.0), k("/a/Conv.bias", "Add", 0.5), k("/b/body.0/Conv", "Conv", 1.5), k("x", "Reshape", 1.0)], &costs());
        assert_eq!(p.kernel_ms, 4.0);
        assert_eq!(p.by_op[0].op, "Conv");
        assert!((p.by_op[0].share - 0.625).abs() < 1e-12);
        let a = p.layers.iter().find(|l| l.node == "/a/Conv").unwrap();
        assert_eq!((a.ms, a.op.as_str(), a.macs), (1.5, "Conv+Add", 1000));
        assert!((a.gmacs_per_s.unwrap() - 1000.0 / 1.5e-3 / 1e9).abs() < 1e-12);
        assert!(p.layers.iter().any(|l| l.node == "x" && l.macs == 0 && l.gmacs_per_s.is_none()));
        assert_eq!(p.macs, 1500);
        assert_eq!(p.best_gmacs_per_s, 0.0, "no layer of 1 M MACs");
    }
}
