//! `pdi-compile inspect`: what a model is, what it costs, and which parts are which.
//!
//! JSON fields (`inspect --json`) are documented on the structs below and in README.md.

use crate::analysis::{bridge, head, partition};
use crate::ir::{cost, infer, Graph};
use crate::onnx::proto::ModelProto;
use anyhow::{anyhow, Result};
use serde::Serialize;
use std::collections::{BTreeMap, HashMap};

#[derive(Serialize)]
pub struct Report {
    pub ir_version: i64,
    /// Opset imports; domain "" is the default ONNX domain.
    pub opsets: Vec<(String, i64)>,
    pub producer: String,
    pub inputs: Vec<ValueSummary>,
    pub outputs: Vec<ValueSummary>,
    pub nodes: usize,
    /// Op type -> node count.
    pub ops: BTreeMap<String, usize>,
    /// Float (and int8) initializer elements, split by part.
    pub params: Split,
    /// Elements of constant tensors that are not learned parameters (PSF gate maps, decode grids).
    pub constants: u64,
    /// Multiply-accumulates of Conv/ConvTranspose/Gemm/MatMul, split by part.
    pub macs: Split,
    pub bridge: bridge::Bridge,
    pub head: head::Head,
    pub warnings: Vec<String>,
}

#[derive(Serialize)]
pub struct ValueSummary {
    pub name: String,
    pub dtype: Option<crate::tensor::DType>,
    /// -1 for dimensions not fixed in the file.
    pub shape: Option<Vec<i64>>,
    /// Outputs only: "reconstruction" or "detection".
    #[serde(skip_serializing_if = "Option::is_none")]
    pub role: Option<&'static str>,
}

/// A quantity split into reconstruction-only, detection-only and shared parts; `total`
/// also counts what feeds no output (`dead`).
#[derive(Serialize, Default, Clone, Copy)]
pub struct Split {
    pub total: u64,
    pub reconstruction_only: u64,
    pub detection_only: u64,
    pub shared: u64,
    pub dead: u64,
}

impl Split {
    fn add(&mut self, part: partition::Part, v: u64) {
        self.total += v;
        match part {
            partition::Part::ReconstructionOnly => self.reconstruction_only += v,
            partition::Part::DetectionOnly => self.detection_only += v,
            partition::Part::Shared => self.shared += v,
            partition::Part::Dead => self.dead += v,
        }
    }
}

pub fn inspect(model: &ModelProto) -> Result<Report> {
    let gp = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let g = Graph::build(gp)?;
    let inf = infer(&g);
    let part = partition::partition(&g, &inf);

    let mut ops = BTreeMap::new();
    let mut macs = Split::default();
    let mut param_part: HashMap<&str, (u64, Option<partition::Part>)> = HashMap::new();
    for (i, node) in gp.node.iter().enumerate() {
        *ops.entry(node.op_type.clone()).or_insert(0) += 1;
        macs.add(part.parts[i], cost::macs(node, &inf));
        for (name, n) in cost::params_of(node, &g) {
            let e = param_part.entry(name).or_insert((n, None));
            e.1 = Some(partition::combine(e.1, part.parts[i]));
        }
    }
    let mut params = Split::default();
    for (n, p) in param_part.values() {
        params.add(p.unwrap_or(partition::Part::Dead), *n);
    }
    let constants: u64 = {
        let mut seen: HashMap<&str, u64> = HashMap::new();
        for node in &gp.node {
            seen.extend(cost::constants_of(node, &g));
        }
        seen.iter().filter(|(k, _)| !param_part.contains_key(*k)).map(|(_, v)| v).sum()
    };

    let summary = |v: &crate::onnx::proto::ValueInfoProto, role: Option<&'static str>| {
        let t = inf.types.get(&v.name).cloned().unwrap_or_default();
        ValueSummary { name: v.name.clone(), dtype: t.dtype, shape: t.shape, role }
    };
    let outputs = gp
        .output
        .iter()
        .map(|o| summary(o, Some(if part.recon_outputs.contains(&o.name) { "reconstruction" } else { "detection" })))
        .collect();
    let mut warnings = inf.warnings.clone();
    if part.recon_outputs.is_empty() {
        warnings.push("no output is shaped like the image input: no reconstruction branch recognized".into());
    }
    Ok(Report {
        ir_version: model.ir_version,
        opsets: model.opset_import.iter().map(|o| (o.domain.clone(), o.version)).collect(),
        producer: format!("{} {}", model.producer_name, model.producer_version).trim().to_string(),
        inputs: g.inputs.iter().map(|v| summary(v, None)).collect(),
        outputs,
        nodes: gp.node.len(),
        ops,
        params,
        constants,
        macs,
        bridge: bridge::find(&g, &inf, part.image_input.as_deref()),
        head: head::detect(&g, &inf, &part.det_outputs),
        warnings,
    })
}

fn shape_str(s: &Option<Vec<i64>>) -> String {
    match s {
        Some(s) => format!("[{}]", s.iter().map(|d| if *d < 0 { "?".into() } else { d.to_string() }).collect::<Vec<_>>().join(", ")),
        None => "unknown".into(),
    }
}

fn dtype_str(d: Option<crate::tensor::DType>) -> String {
    d.map_or("?".into(), |d| format!("{d:?}").to_lowercase())
}

fn human(n: u64) -> String {
    match n {
        n if n >= 1_000_000_000 => format!("{:.2} G", n as f64 / 1e9),
        n if n >= 1_000_000 => format!("{:.2} M", n as f64 / 1e6),
        n if n >= 1_000 => format!("{:.1} k", n as f64 / 1e3),
        n => n.to_string(),
    }
}

impl Report {
    pub fn render(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let opsets: Vec<String> = self.opsets.iter().map(|(d, v)| format!("{}:{v}", if d.is_empty() { "ai.onnx" } else { d })).collect();
        let _ = writeln!(s, "IR {}  opsets {}  producer {}", self.ir_version, opsets.join(", "), self.producer);
        for v in &self.inputs {
            let _ = writeln!(s, "input   {:<14} {} {}", v.name, dtype_str(v.dtype), shape_str(&v.shape));
        }
        for v in &self.outputs {
            let _ = writeln!(s, "output  {:<14} {} {}  ({})", v.name, dtype_str(v.dtype), shape_str(&v.shape), v.role.unwrap_or(""));
        }
        let _ = writeln!(s, "\n{:<12} {:>12} {:>12} {:>12} {:>12}", "", "total", "recon-only", "det-only", "shared");
        for (name, v) in [("params", self.params), ("MACs", self.macs)] {
            let _ = writeln!(s, "{:<12} {:>12} {:>12} {:>12} {:>12}", name, human(v.total), human(v.reconstruction_only), human(v.detection_only), human(v.shared));
        }
        let _ = writeln!(s, "{:<12} {:>12}  (gate maps, grids: not parameters)", "constants", human(self.constants));
        let classes = self.head.classes.map_or("?".into(), |c| c.to_string());
        let _ = writeln!(s, "\nhead: {:?}, {classes} classes, output '{}'", self.head.kind, self.head.output.as_deref().unwrap_or("?"));
        match self.bridge.blur_maps.first() {
            Some(b) => {
                let _ = writeln!(s, "PALS-Bridge: blur map '{}' {:?} ({}), {} gate(s)", b.name, b.shape, b.source, self.bridge.gates.len());
                for gt in &self.bridge.gates {
                    let _ = writeln!(s, "  gate {:<10} modulation {:<4} branch {:<10} ({} nodes)", gt.clip_node, gt.modulation, gt.branch, gt.subgraph_nodes);
                }
            }
            None => s.push_str("PALS-Bridge: not found\n"),
        }
        let ops: Vec<String> = self.ops.iter().map(|(k, v)| format!("{k} {v}")).collect();
        let _ = writeln!(s, "\n{} nodes: {}", self.nodes, ops.join(", "));
        for w in &self.warnings {
            let _ = writeln!(s, "warning: {w}");
        }
        s
    }
}

#[derive(Serialize, Clone, Copy)]
pub struct Counts {
    pub nodes: usize,
    pub params: u64,
    pub macs: u64,
}

pub fn counts(model: &ModelProto) -> Result<Counts> {
    let r = inspect(model)?;
    Ok(Counts { nodes: r.nodes, params: r.params.total, macs: r.macs.total })
}
