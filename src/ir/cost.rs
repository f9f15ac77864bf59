//! Parameters and multiply-accumulates per node, from inferred shapes.
//!
//! MACs count the multiply-adds of Conv, ConvTranspose, Gemm and MatMul only: element-wise
//! ops are memory-bound and are not what "GFLOPs" in detector papers counts.

use super::{graph::Graph, shapes::Inferred};
use crate::onnx::attr;
use crate::onnx::proto::NodeProto;
use crate::tensor::DType;

/// Multiply-accumulates of one node (0 for ops that do none or whose shapes are unknown).
pub fn macs(node: &NodeProto, inf: &Inferred) -> u64 {
    let shape = |i: usize| node.input.get(i).and_then(|n| inf.shape(n));
    let out = node.output.first().and_then(|n| inf.shape(n));
    let prod = |s: &[usize]| s.iter().map(|&d| d as u64).product::<u64>();
    match node.op_type.as_str() {
        "Conv" | "ConvInteger" | "QLinearConv" => {
            let w = if node.op_type == "QLinearConv" { shape(3) } else { shape(1) };
            match (out, w) {
                // out elements x (Cin/group x kernel area) = out x prod(W[1..])
                (Some(o), Some(w)) if !w.is_empty() => prod(&o) * prod(&w[1..]),
                _ => 0,
            }
        }
        "ConvTranspose" => match (shape(0), shape(1)) {
            // every input element scatters into Cout/group x kernel area outputs
            (Some(x), Some(w)) if w.len() > 1 => prod(&x) * prod(&w[1..]),
            _ => 0,
        },
        "Gemm" => match (out, shape(0)) {
            (Some(o), Some(a)) if a.len() == 2 => {
                let k = if attr::int(node, "transA", 0) != 0 { a[0] } else { a[1] };
                prod(&o) * k as u64
            }
            _ => 0,
        },
        "MatMul" | "MatMulInteger" => match (out, shape(0)) {
            (Some(o), Some(a)) if !a.is_empty() => prod(&o) * *a.last().unwrap() as u64,
            _ => 0,
        },
        _ => 0,
    }
}

/// Ops whose constant inputs are learned weights.
const WEIGHTED_OPS: &[&str] = &[
    "Conv", "ConvTranspose", "Gemm", "MatMul", "BatchNormalization", "InstanceNormalization", "LayerNormalization", "PRelu",
    "QLinearConv", "ConvInteger", "QLinearMatMul", "MatMulInteger", "DequantizeLinear",
];

/// Learned parameters read by `node`: the float (or int8/uint8 quantized) constants of
/// weighted layers, and per-channel scale/shift constants of element-wise ops (folded
/// BatchNorm). Not parameters: precomputed maps such as folded PSF gates ([1, 1, H, W]) or
/// decode grids, and integer shape arguments; [`constants_of`] counts those.
pub fn params_of<'g>(node: &'g NodeProto, g: &Graph<'g>) -> Vec<(&'g str, u64)> {
    numeric_constants(node, g).filter(|(_, t)| WEIGHTED_OPS.contains(&node.op_type.as_str()) || per_channel(&t.dims)).map(|(n, t)| (n, elements(&t.dims))).collect()
}

/// Constant tensors read by `node` that are not parameters (see [`params_of`]).
pub fn constants_of<'g>(node: &'g NodeProto, g: &Graph<'g>) -> Vec<(&'g str, u64)> {
    numeric_constants(node, g).filter(|(_, t)| !(WEIGHTED_OPS.contains(&node.op_type.as_str()) || per_channel(&t.dims))).map(|(n, t)| (n, elements(&t.dims))).collect()
}

fn numeric_constants<'a, 'g>(node: &'g NodeProto, g: &'a Graph<'g>) -> impl Iterator<Item = (&'g str, &'g crate::onnx::proto::TensorProto)> + use<'a, 'g> {
    node.input.iter().filter_map(|n| {
        // Paddle and tf2onnx store weights in Constant nodes rather than initializers.
        let t = match g.initializers.get(n.as_str()) {
            Some(t) => *t,
            None => g.producer_of(n).filter(|p| p.op_type == "Constant").and_then(|p| crate::onnx::attr::tensor(p, "value"))?,
        };
        let counts = DType::from_onnx(t.data_type).is_some_and(|d| d.is_float() || matches!(d, DType::I8 | DType::U8));
        counts.then_some((n.as_str(), t))
    })
}

/// [1, C, 1, 1]-like: only the channel axis (third from the right) is longer than 1.
fn per_channel(dims: &[i64]) -> bool {
    let r = dims.len();
    r >= 3 && dims[r - 3] > 1 && dims.iter().enumerate().all(|(i, &d)| i == r - 3 || d == 1)
}

fn elements(dims: &[i64]) -> u64 {
    dims.iter().map(|&d| d.max(0) as u64).product()
}
