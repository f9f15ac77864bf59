//! Recognizing the PALS-Bridge's PSF gates.
//!
//! A gate is `clip(sigmoid(theta) + alpha * m(k), 0, 1)` where `k` is the 6x8 blur map
//! resized to the feature's H x W and `m(k)` is `k` or `1 - k`. We find the Resize of a
//! small [1, 1, h, w] value (a graph input or a constant), follow element-wise arithmetic
//! forward to each Clip, and classify the branch each gate multiplies by walking back from
//! the other operand of the gate's Mul to its convolution.

use crate::ir::{Graph, Inferred};
use crate::onnx::attr;
use crate::onnx::proto::NodeProto;
use serde::Serialize;
use std::collections::{HashSet, VecDeque};

/// Blur maps are coarse grids; anything larger than this is a feature map, not a PSF prior.
const MAX_BLUR_CELLS: usize = 4096;

#[derive(Clone, Debug, Serialize)]
pub struct BlurMap {
    /// "input" when a deployment must feed it, "constant" when baked into the graph.
    pub source: &'static str,
    pub name: String,
    pub shape: Vec<usize>,
    /// The Resize bringing it to the feature's H x W.
    pub resize_node: String,
    pub resized_shape: Option<Vec<usize>>,
}

#[derive(Clone, Debug, Serialize)]
pub struct Gate {
    /// The Clip (or Min) node that bounds the gate to [0, 1].
    pub clip_node: String,
    pub gate_value: String,
    /// "k" (large branch) or "1-k" (small and Laplacian branches).
    pub modulation: &'static str,
    /// "small", "large", "laplacian" or "unknown".
    pub branch: &'static str,
    /// The Mul computing gate (.) branch, when found.
    pub product_node: Option<String>,
    pub branch_value: Option<String>,
    /// Nodes computing the gate from theta, alpha and the blur map (not from the image).
    pub subgraph_nodes: usize,
}

#[derive(Clone, Debug, Serialize, Default)]
pub struct Bridge {
    pub blur_maps: Vec<BlurMap>,
    pub gates: Vec<Gate>,
}

pub fn find(g: &Graph, inf: &Inferred, image_input: Option<&str>) -> Bridge {
    let image_dependent = forward_reach(g, image_input.into_iter().collect());
    let mut out = Bridge::default();
    for &i in &g.order {
        let n = g.node(i);
        if n.op_type != "Resize" && n.op_type != "Upsample" {
            continue;
        }
        let Some((source, name, shape)) = blur_source(g, inf, &n.input[0], image_input) else { continue };
        let k = n.output[0].as_str();
        out.blur_maps.push(BlurMap { source, name, shape, resize_node: n.name.clone(), resized_shape: inf.shape(k) });
        for (clip, one_minus) in gates_from(g, k) {
            out.gates.push(describe_gate(g, inf, clip, one_minus, &image_dependent));
        }
    }
    out
}

/// Follows Identity/Cast back from a Resize input to a small [1, 1, h, w] input or constant.
fn blur_source(g: &Graph, inf: &Inferred, value: &str, image: Option<&str>) -> Option<(&'static str, String, Vec<usize>)> {
    let mut v = value;
    while let Some(p) = g.producer_of(v).filter(|p| matches!(p.op_type.as_str(), "Identity" | "Cast")) {
        v = &p.input[0];
    }
    let shape = inf.shape(v)?;
    let small = shape.len() == 4 && shape[0] == 1 && shape[1] == 1 && shape[2] >= 2 && shape[3] >= 2 && shape[2] * shape[3] <= MAX_BLUR_CELLS;
    if !small || Some(v) == image {
        return None;
    }
    let is_input = g.inputs.iter().any(|i| i.name == v);
    let is_const = g.initializers.contains_key(v) || g.producer_of(v).is_some_and(|p| p.op_type == "Constant");
    match (is_input, is_const) {
        (true, _) => Some(("input", v.to_string(), shape)),
        (false, true) => Some(("constant", v.to_string(), shape)),
        _ => None,
    }
}

const GATE_ARITHMETIC: &[&str] = &["Sub", "Mul", "Add", "Div", "Neg", "Cast", "Identity", "Max", "Unsqueeze", "Expand"];

/// Clip nodes reached from `k` through element-wise arithmetic; true where a `1 - k` was taken.
fn gates_from<'g>(g: &Graph<'g>, k: &'g str) -> Vec<(&'g NodeProto, bool)> {
    let mut found = Vec::new();
    let mut queue: VecDeque<(&str, bool)> = VecDeque::from([(k, false)]);
    let mut seen = HashSet::new();
    while let Some((v, flipped)) = queue.pop_front() {
        for &c in g.consumers_of(v) {
            let n = g.node(c);
            if !seen.insert((c, flipped)) {
                continue;
            }
            let is_clamp = n.op_type == "Clip" || n.op_type == "Min";
            if is_clamp {
                found.push((n, flipped));
            } else if GATE_ARITHMETIC.contains(&n.op_type.as_str()) {
                let flips = n.op_type == "Sub" && n.input.get(1).map(|s| s.as_str()) == Some(v) || n.op_type == "Neg";
                queue.push_back((&n.output[0], flipped ^ flips));
            }
        }
    }
    found
}

fn describe_gate(g: &Graph, inf: &Inferred, clip: &NodeProto, one_minus: bool, image_dependent: &HashSet<usize>) -> Gate {
    let gate = clip.output[0].as_str();
    let cone = g.cone([gate]);
    let subgraph_nodes = cone.iter().enumerate().filter(|&(i, &c)| c && !image_dependent.contains(&i)).count();
    let product = g.consumers_of(gate).iter().map(|&c| g.node(c)).find(|n| n.op_type == "Mul");
    let branch_value = product.and_then(|m| m.input.iter().find(|s| s.as_str() != gate)).cloned();
    let branch = branch_value.as_deref().map_or("unknown", |b| classify_branch(g, inf, b));
    Gate {
        clip_node: clip.name.clone(),
        gate_value: gate.to_string(),
        modulation: if one_minus { "1-k" } else { "k" },
        branch,
        product_node: product.map(|p| p.name.clone()),
        branch_value,
        subgraph_nodes,
    }
}

fn forward_reach(g: &Graph, start: Vec<&str>) -> HashSet<usize> {
    let mut seen = HashSet::new();
    let mut stack = start;
    while let Some(v) = stack.pop() {
        for &c in g.consumers_of(v) {
            if seen.insert(c) {
                stack.extend(g.node(c).output.iter().map(|s| s.as_str()));
            }
        }
    }
    seen
}

/// Walks back through BN and SiLU to the branch's convolution and names the branch.
pub fn classify_branch(g: &Graph, inf: &Inferred, value: &str) -> &'static str {
    let Some(conv) = branch_conv(g, value) else { return "unknown" };
    let (k, groups, out_ch) = conv_geometry(conv, inf);
    if k == Some((1, 1)) {
        let prev = g.producer_of(&conv.input[0]).filter(|p| p.op_type == "Conv");
        if let Some((Some((kh, kw)), grp, ch)) = prev.map(|p| conv_geometry(p, inf)) {
            if kh >= 7 && kw >= 7 && Some(grp) == ch {
                return "large";
            }
        }
        return "unknown";
    }
    match k {
        Some((3, 3)) if groups > 1 && Some(groups) == out_ch => "laplacian",
        Some((3, 3)) => "small",
        _ => "unknown",
    }
}

fn branch_conv<'g>(g: &Graph<'g>, value: &str) -> Option<&'g NodeProto> {
    let mut v = value.to_string();
    for _ in 0..8 {
        let p = g.producer_of(&v)?;
        match p.op_type.as_str() {
            "Conv" => return Some(p),
            "BatchNormalization" | "Identity" | "Relu" | "Sigmoid" => v = p.input[0].clone(),
            // SiLU exported as x * sigmoid(x): continue along x.
            "Mul" => {
                let sig = p.input.iter().position(|s| g.producer_of(s).is_some_and(|q| q.op_type == "Sigmoid"))?;
                v = p.input[1 - sig].clone();
            }
            _ => return None,
        }
    }
    None
}

/// ((kh, kw), group, output channels) of a Conv.
fn conv_geometry(conv: &NodeProto, inf: &Inferred) -> (Option<(usize, usize)>, usize, Option<usize>) {
    let w = conv.input.get(1).and_then(|n| inf.shape(n));
    let k = attr::ints(conv, "kernel_shape")
        .filter(|k| k.len() == 2)
        .map(|k| (k[0] as usize, k[1] as usize))
        .or_else(|| w.as_ref().filter(|w| w.len() == 4).map(|w| (w[2], w[3])));
    (k, attr::int(conv, "group", 1).max(1) as usize, w.map(|w| w[0]))
}
