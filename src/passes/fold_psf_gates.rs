//! `fold-psf-gates`: the PALS-Bridge's constant gates, folded.
//!
//! After `bind-psf` and `fold-constants` each gate g = clip(sigmoid(theta) + alpha m(k), 0, 1)
//! is a constant [1, 1, H, W] map multiplying its branch, and the fusion reads
//! y = x + eta (g_s s + g_l l + g_lam lam). This pass
//! - folds eta into the gates (one Mul fewer on a full feature map);
//! - removes a branch whose gate is 0 everywhere (the branch's convs go with it);
//! - folds a spatially uniform gate c into the branch's last Conv or BatchNormalization
//!   (scaling weights and bias), or makes it a scalar where the branch ends in an activation;
//! - keeps spatially varying gates as constant maps.
//!
//! Needs: constant gates (run after bind-psf and fold-constants). Guarantees: same outputs up
//! to float rounding of the folded products. Reports: each gate's min, mean, max and action.

use crate::analysis::bridge::classify_branch;
use crate::ir::{infer, Graph};
use crate::onnx::edit::{fresh_name, initializer, remove_nodes, replace_value, set_initializer};
use crate::onnx::proto::{GraphProto, ModelProto};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use super::{Pass, PassContext};
use crate::tensor::Tensor;
use anyhow::Result;
use std::collections::HashSet;

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// A gate whose values all lie within this of each other is treated as uniform. 1e-7 is
    /// about one f32 ulp at 1: it only catches maps that are constant up to rounding.
    pub uniform_tolerance: f32,
}

impl Default for Options {
    fn default() -> Self {
        Options { uniform_tolerance: 1e-7 }
    }
}

pub struct FoldPsfGates {
    pub options: Options,
}

/// One gate (.) branch product found in the graph.
struct Product {
    node: usize,
    gate: String,
    branch: String,
}

impl Pass for FoldPsfGates {
    fn name(&self) -> &'static str {
        "fold-psf-gates"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let g = super::graph_mut(model)?;
        let fusions = find_fusions(g)?;
        if fusions.is_empty() {
            let note = if has_bridge(g)? { "no constant gate products found (run bind-psf and fold-constants first)" } else { "no PALS-Bridge in the model: no PSF gates to fold (not a PDI-Net export)" };
            return Ok(serde_json::json!({ "gates": [], "note": note }));
        }
        let mut dead = HashSet::new();
        let mut gates_report = Vec::new();
        for f in fusions {
            if let Some((eta_node, eta)) = f.eta {
                let (out, root) = (g.node[eta_node].output[0].clone(), f.root.clone());
                if replace_value(g, &out, &root) {
                    dead.insert(eta_node);
                    for p in &f.products {
                        scale_gate(g, p, eta)?;
                    }
                }
            }
            for p in &f.products {
                gates_report.push(fold_one(g, p, self.options.uniform_tolerance, &mut dead)?);
            }
        }
        remove_nodes(g, &dead);
        crate::ir::rewrite::dce::eliminate(g)?;
        Ok(serde_json::json!({ "gates": gates_report }))
    }
}

struct Fusion {
    /// The Mul by eta and eta's value, when present.
    eta: Option<(usize, f32)>,
    /// The value summing the gated branches.
    root: String,
    products: Vec<Product>,
}

fn gate_product(g: &GraphProto, graph: &Graph, value: &str) -> Option<Product> {
    let &i = graph.producer.get(value)?;
    let n = &g.node[i];
    if n.op_type != "Mul" || n.input.len() != 2 {
        return None;
    }
    for (gi, bi) in [(0, 1), (1, 0)] {
        let Some(t) = initializer(g, &n.input[gi]) else { continue };
        let spatial = t.dims.len() == 4 && t.dims[0] == 1 && t.dims[1] == 1 && t.dims[2] * t.dims[3] > 1;
        let in_unit = to_tensor(t).ok().and_then(|t| t.as_f32().map(|v| v.iter().all(|x| (0.0..=1.0).contains(x))));
        if spatial && in_unit == Some(true) && initializer(g, &n.input[bi]).is_none() {
            return Some(Product { node: i, gate: n.input[gi].clone(), branch: n.input[bi].clone() });
        }
    }
    None
}

/// Leaves of the Add tree rooted at `value` (Adds used only inside the tree).
fn add_leaves(g: &GraphProto, graph: &Graph, value: &str, out: &mut Vec<String>) {
    match graph.producer.get(value).map(|&i| &g.node[i]) {
        Some(n) if n.op_type == "Add" && graph.consumers_of(value).len() <= 1 => {
            for i in &n.input {
                add_leaves(g, graph, i, out);
            }
        }
        _ => out.push(value.to_string()),
    }
}

fn find_fusions(g: &GraphProto) -> Result<Vec<Fusion>> {
    let graph = Graph::build(g)?;
    let mut fusions = Vec::new();
    let mut claimed = HashSet::new();
    // Roots: Adds whose leaves are all gate products (two or more of them).
    for &i in graph.order.iter().rev() {
        let n = &g.node[i];
        if n.op_type != "Add" || claimed.contains(&i) {
            continue;
        }
        let mut leaves = Vec::new();
        add_leaves(g, &graph, &n.output[0], &mut leaves);
        let products: Option<Vec<Product>> = leaves.iter().map(|l| gate_product(g, &graph, l)).collect();
        let Some(products) = products.filter(|p| p.len() >= 2) else { continue };
        mark_tree(g, &graph, &n.output[0], &mut claimed);
        let root = n.output[0].clone();
        let eta = match graph.consumers_of(&root) {
            [c] if g.node[*c].op_type == "Mul" => {
                let m = &g.node[*c];
                m.input.iter().find(|x| **x != root).and_then(|e| initializer(g, e)).and_then(|t| to_tensor(t).ok()).filter(|t| t.len() == 1).and_then(|t| t.as_f32().map(|v| (*c, v[0])))
            }
            _ => None,
        };
        fusions.push(Fusion { eta, root, products });
    }
    Ok(fusions)
}

fn mark_tree(g: &GraphProto, graph: &Graph, value: &str, claimed: &mut HashSet<usize>) {
    if let Some(&i) = graph.producer.get(value) {
        if g.node[i].op_type == "Add" && claimed.insert(i) {
            for inp in &g.node[i].input {
                mark_tree(g, graph, inp, claimed);
            }
        }
    }
}

fn gate_values(g: &GraphProto, name: &str) -> Result<Tensor> {
    to_tensor(initializer(g, name).ok_or_else(|| anyhow::anyhow!("gate {name} vanished"))?)
}

/// gate <- eta * gate, under a fresh name (the original may be shared).
fn scale_gate(g: &mut GraphProto, p: &Product, eta: f32) -> Result<()> {
    let t = gate_values(g, &p.gate)?;
    let v: Vec<f32> = t.as_f32().unwrap_or_default().iter().map(|x| x * eta).collect();
    let name = fresh_name(g, &format!("{}_eta", p.gate));
    set_initializer(g, from_tensor(&name, &Tensor::f32(t.shape.clone(), v)));
    let n = &mut g.node[p.node];
    for i in n.input.iter_mut().filter(|i| **i == p.gate) {
        *i = name.clone();
    }
    Ok(())
}

fn fold_one(g: &mut GraphProto, p: &Product, tol: f32, dead: &mut HashSet<usize>) -> Result<serde_json::Value> {
    let gate_name = g.node[p.node].input.iter().find(|i| **i != p.branch).cloned().unwrap_or_default();
    let t = gate_values(g, &gate_name)?;
    let v = t.as_f32().unwrap_or_default();
    let (lo, hi) = v.iter().fold((f32::MAX, f32::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    let mean = v.iter().map(|&x| x as f64).sum::<f64>() / v.len().max(1) as f64;
    let kind = {
        let graph = Graph::build(g)?;
        classify_branch(&graph, &infer(&graph), &p.branch)
    };
    let product_out = g.node[p.node].output[0].clone();
    let action = if hi == 0.0 && lo == 0.0 {
        remove_term(g, p, dead)?
    } else if hi - lo <= tol * hi.abs().max(1.0) {
        fold_uniform(g, p, mean as f32, dead)?
    } else {
        "spatial gate kept as a constant map".to_string()
    };
    Ok(serde_json::json!({ "gate": p.gate, "product": product_out, "branch": kind, "min": lo, "mean": mean, "max": hi, "action": action }))
}

/// Drops `gate (.) branch` from its Add: the Add forwards its other operand.
fn remove_term(g: &mut GraphProto, p: &Product, dead: &mut HashSet<usize>) -> Result<String> {
    let out = g.node[p.node].output[0].clone();
    let graph = Graph::build(g)?;
    let Some(&a) = graph.consumers_of(&out).first() else { return Ok("zero gate, but its product is unused".into()) };
    drop(graph);
    let add = g.node[a].clone();
    let other = add.input.iter().find(|i| **i != out).cloned();
    match other {
        Some(other) if add.op_type == "Add" && replace_value(g, &add.output[0], &other) => {
            dead.insert(a);
            dead.insert(p.node);
            Ok("zero everywhere: branch removed".into())
        }
        _ => Ok("zero everywhere, but its sum could not be rewired: kept".into()),
    }
}

/// A uniform gate c scales the branch's last Conv or BN; otherwise it becomes a scalar.
fn fold_uniform(g: &mut GraphProto, p: &Product, c: f32, dead: &mut HashSet<usize>) -> Result<String> {
    let graph = Graph::build(g)?;
    let producer = graph.producer.get(p.branch.as_str()).copied();
    let single_use = graph.consumers_of(&p.branch).len() == 1;
    drop(graph);
    if let (Some(i), true) = (producer, single_use) {
        let node = g.node[i].clone();
        let params: &[usize] = match node.op_type.as_str() {
            "Conv" | "ConvTranspose" => &[1, 2],
            "BatchNormalization" => &[1, 2], // gamma, beta
            _ => &[],
        };
        let all_const = !params.is_empty() && params.iter().all(|&k| node.input.get(k).is_some_and(|n| initializer(g, n).is_some()));
        if all_const {
            for &k in params {
                let t = to_tensor(initializer(g, &node.input[k]).expect("checked"))?;
                let v: Vec<f32> = t.as_f32().unwrap_or_default().iter().map(|x| x * c).collect();
                let name = fresh_name(g, &format!("{}_gated", node.input[k]));
                set_initializer(g, from_tensor(&name, &Tensor::f32(t.shape.clone(), v)));
                g.node[i].input[k] = name;
            }
            let out = g.node[p.node].output[0].clone();
            if replace_value(g, &out, &p.branch) {
                dead.insert(p.node);
                return Ok(format!("uniform {c}: folded into {} '{}'", node.op_type, node.name));
            }
        }
    }
    let name = fresh_name(g, &format!("{}_scalar", p.gate));
    set_initializer(g, from_tensor(&name, &Tensor::f32(vec![1], vec![c])));
    let n = &mut g.node[p.node];
    for i in n.input.iter_mut().filter(|i| **i != p.branch) {
        *i = name.clone();
    }
    Ok(format!("uniform {c}: scalar multiply (branch ends in an activation)"))
}

/// Whether the model has PSF gates at all (folded or not): a plain detector has none.
fn has_bridge(g: &GraphProto) -> Result<bool> {
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let image = crate::analysis::partition::image_input(&graph, &inf);
    let b = crate::analysis::bridge::find(&graph, &inf, image.as_deref());
    Ok(!b.gates.is_empty() || !b.blur_maps.is_empty())
}
