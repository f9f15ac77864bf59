//! Which nodes run in integers, which stay float, and which values share parameters.
//!
//! The rules are those of a QDQ graph ONNX Runtime fuses into integer kernels: a quantized
//! node reads dequantized activations and (for Conv) per-channel int8 weights and an int32
//! bias, and its output is quantized again. The detector's head convolutions read quantized
//! activations but write float: their output channels mix box coordinates (hundreds of
//! pixels) with objectness and class logits, and one scale across them would crush the scores.
//! Everything after them (the decode) is float too.

use crate::analysis::channels::head_convolutions;
use crate::ir::Graph;
use crate::onnx::tensor_proto::to_tensor;
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};

/// Ops whose output is one of their input's values (or a subset): the output shares the
/// input's scale, so ONNX Runtime drops the Q/DQ pair around them instead of requantizing.
const DATA_MOVEMENT: &[&str] = &["MaxPool", "Resize", "Split", "Slice"];
/// Ops ONNX Runtime has integer kernels for in QDQ form, with their activation input slots.
const ARITHMETIC: &[&str] = &["Add", "Mul", "Concat"];
const UNARY: &[&str] = &["Sigmoid", "AveragePool", "GlobalAveragePool"];
/// Ops that pick one of their inputs' values: quantized when every input shares one set of
/// parameters, and then computed on the integer codes themselves (`qdq::on_codes`), since
/// ONNX Runtime has no QDQ fusion for them (`space-to-depth`'s pooling, a Max).
pub const ON_CODES: &[&str] = &["Max"];

#[derive(Clone, Debug, Default)]
pub struct Plan {
    /// Nodes computed on quantized values.
    pub quantized: BTreeSet<usize>,
    /// Quantized nodes whose outputs stay float (head convolutions, graph outputs).
    pub float_output: BTreeSet<usize>,
    /// Nodes left in float, with the reason.
    pub float: BTreeMap<usize, String>,
    /// Value -> the value whose quantization parameters it uses.
    pub shares: HashMap<String, String>,
    /// A quantized node's output read only by a Relu -> that Relu: the value gets no Q/DQ pair
    /// of its own; the Relu's output quantization clamps at zero (its range starts there, so
    /// its zero point is the lowest code) and emission removes the Relu, as ONNX Runtime's own
    /// quantizer does. The producer's codes then cover [0, max] instead of wasting about half
    /// of them on negatives the Relu discards, and calibration never reads the value.
    pub fused_relu: BTreeMap<String, usize>,
}

impl Plan {
    /// Input slots of node `i` that carry quantized activations (or constants quantized like them).
    pub fn activation_slots(g: &Graph, i: usize) -> Vec<usize> {
        let n = g.node(i);
        let op = n.op_type.as_str();
        if ARITHMETIC.contains(&op) || ON_CODES.contains(&op) {
            (0..n.input.len()).filter(|&s| !n.input[s].is_empty()).collect()
        } else {
            vec![0]
        }
    }

    /// The value whose parameters `v` uses (itself unless it is a data-movement output).
    pub fn root<'a>(&'a self, mut v: &'a str) -> &'a str {
        while let Some(r) = self.shares.get(v) {
            v = r;
        }
        v
    }

    /// Values that get a Q/DQ pair: outputs of quantized nodes (not float-output ones) and
    /// activation inputs of quantized nodes that are not constants.
    pub fn quantized_values(&self, g: &Graph) -> BTreeSet<String> {
        let mut out = BTreeSet::new();
        for &i in &self.quantized {
            let n = g.node(i);
            for s in Self::activation_slots(g, i) {
                if !g.initializers.contains_key(n.input[s].as_str()) {
                    out.insert(n.input[s].clone());
                }
            }
            if !self.float_output.contains(&i) {
                out.extend(n.output.iter().filter(|o| !o.is_empty()).cloned());
            }
        }
        out.retain(|v| !self.fused_relu.contains_key(v));
        out
    }

    /// Whether `v`'s readers all see the quantized value (its producer writes integers).
    pub fn produced_quantized(&self, g: &Graph, v: &str) -> bool {
        g.producer.get(v).is_some_and(|p| self.quantized.contains(p) && !self.float_output.contains(p))
    }
}

/// The plan for `g`; `keep_float` names nodes (or their output values) to leave in float.
pub fn plan(g: &Graph, keep_float: &HashSet<String>) -> Plan {
    let mut p = Plan::default();
    let heads: HashSet<usize> = head_convolutions(g).into_iter().collect();
    let tail = g.downstream_of(&heads);
    let outputs: HashSet<&str> = g.proto.output.iter().map(|o| o.name.as_str()).collect();
    for &i in &g.order {
        let n = g.node(i);
        let op = n.op_type.as_str();
        if op == "Relu" && fusable_relu(g, &p, i, &outputs, keep_float) {
            p.quantized.insert(i);
            p.fused_relu.insert(n.input[0].clone(), i);
            continue;
        }
        let reason = if tail.contains(&i) {
            Some("detection decode after the head convolutions (boxes and scores stay float)".to_string())
        } else if keep_float.contains(&n.name) || n.output.iter().any(|o| keep_float.contains(o)) {
            Some("kept float (keep_float or mixed precision)".to_string())
        } else if ON_CODES.contains(&op) && !same_codes(g, &p, i) {
            Some(format!("{op} of values quantized with different parameters"))
        } else if !n.domain.is_empty() || !(op == "Conv" || ARITHMETIC.contains(&op) || UNARY.contains(&op) || DATA_MOVEMENT.contains(&op) || ON_CODES.contains(&op) || ones_upsample(g, i)) {
            Some(format!("{op} has no integer kernel in QDQ form"))
        } else if op == "Conv" && !n.input.iter().skip(1).filter(|s| !s.is_empty()).all(|s| float_constant(g, s)) {
            Some("convolution weights are not float constants".to_string())
        } else if Plan::activation_slots(g, i).iter().any(|&s| g.initializers.contains_key(n.input[s].as_str()) && !float_constant(g, &n.input[s])) {
            Some("a constant operand is not float".to_string())
        } else {
            None
        };
        match reason {
            Some(r) => {
                p.float.insert(i, r);
            }
            None => {
                p.quantized.insert(i);
                if heads.contains(&i) || n.output.iter().any(|o| outputs.contains(o.as_str())) {
                    p.float_output.insert(i);
                }
                if DATA_MOVEMENT.contains(&op) || ON_CODES.contains(&op) || op == "ConvTranspose" {
                    for o in n.output.iter().filter(|o| !o.is_empty()) {
                        p.shares.insert(o.clone(), n.input[0].clone());
                    }
                }
            }
        }
    }
    p
}

/// Whether every input of node `i` is the quantized output of a quantized node, all sharing
/// one value's parameters, and its output is not a graph output.
fn same_codes(g: &Graph, p: &Plan, i: usize) -> bool {
    let n = g.node(i);
    let outputs = g.proto.output.iter().any(|o| n.output.contains(&o.name));
    let mut roots = n.input.iter().map(|v| (!v.is_empty() && p.produced_quantized(g, v) && !p.fused_relu.contains_key(v)).then(|| p.root(v)));
    let Some(Some(first)) = roots.next() else { return false };
    !outputs && roots.all(|r| r == Some(first))
}

/// Whether Relu node `i` can run as its producer's output quantization: the producer is
/// quantized with a quantized output that only this Relu reads, and neither value is a graph
/// output nor kept float.
fn fusable_relu(g: &Graph, p: &Plan, i: usize, outputs: &HashSet<&str>, keep_float: &HashSet<String>) -> bool {
    let n = g.node(i);
    let (Some(x), Some(y)) = (n.input.first(), n.output.first()) else { return false };
    let kept = |s: &str| keep_float.contains(s) || outputs.contains(s);
    n.domain.is_empty()
        && !kept(&n.name)
        && !kept(x)
        && !kept(y)
        && g.consumers_of(x) == [i]
        && g.producer.get(x.as_str()).is_some_and(|&q| p.quantized.contains(&q) && !p.float_output.contains(&q) && !p.shares.contains_key(x))
}

fn float_constant(g: &Graph, name: &str) -> bool {
    g.initializers.get(name).and_then(|t| to_tensor(t).ok()).is_some_and(|t| t.as_f32().is_some())
}

/// A depthwise ConvTranspose with a ones kernel and stride = kernel (what `resize-to-deconv`
/// makes of nearest upsampling): every output is one input value, so it moves data.
fn ones_upsample(g: &Graph, i: usize) -> bool {
    let n = g.node(i);
    if n.op_type != "ConvTranspose" || n.input.len() > 2 {
        return false;
    }
    let Some(w) = n.input.get(1).and_then(|w| g.initializers.get(w.as_str())).and_then(|t| to_tensor(t).ok()) else { return false };
    let kernel: Vec<i64> = w.shape.iter().skip(2).map(|&d| d as i64).collect();
    let strides = crate::onnx::attr::ints(n, "strides").unwrap_or_default();
    w.as_f32().is_some_and(|v| v.iter().all(|&x| x == 1.0)) && strides == kernel && w.shape.get(1) == Some(&1)
}
