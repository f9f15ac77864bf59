//! `fold-bn`: BatchNormalization folded into the Conv/ConvTranspose before it.
//!
//! y = gamma (conv(x) - mean) / sqrt(var + eps) + beta  =>  W' = W s, b' = (b - mean) s + beta,
//! with s = gamma / sqrt(var + eps). The arithmetic is f32 in exactly ONNX Runtime's order
//! (its ConvBNFusion): ORT fuses the original the same way, so the folded weights are the
//! ones ORT would run and the candidate's outputs match the reference's bit for bit where
//! ORT fuses. A channel whose var + eps is not a positive normal number would give an
//! infinite scale: that BN is left alone and named.
//! A BN with no foldable producer becomes Mul + Add with per-channel constants, which ORT
//! and tract fuse into neighbouring element-wise work and RKNN maps to its EW unit.
//! Needs: constant BN parameters and conv weights (run after fold-constants).
//! Reports: BNs folded into convs, BNs turned into Mul+Add, BNs left (with the reason).

use crate::ir::Graph;
use crate::onnx::attr;
use crate::onnx::edit::{fresh_name, initializer, remove_nodes, replace_value, set_initializer, set_input_constant};
use crate::onnx::proto::{GraphProto, ModelProto, NodeProto};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use super::{Pass, PassContext};
use crate::tensor::Tensor;
use anyhow::Result;
use std::collections::HashSet;

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// Turn BNs without a conv before them into Mul + Add.
    pub standalone_to_mul_add: bool,
}

impl Default for Options {
    fn default() -> Self {
        Options { standalone_to_mul_add: true }
    }
}

pub struct FoldBn {
    pub options: Options,
}

struct BnParams {
    scale: Vec<f32>,
    mean: Vec<f32>,
    beta: Vec<f32>,
}

impl BnParams {
    /// The bias after folding, as ORT computes it: (b - mean) * s + beta, or beta - mean * s.
    fn bias(&self, conv_bias: Option<&[f32]>) -> Vec<f32> {
        (0..self.scale.len())
            .map(|c| match conv_bias {
                Some(b) => (b[c] - self.mean[c]) * self.scale[c] + self.beta[c],
                None => self.beta[c] - self.mean[c] * self.scale[c],
            })
            .collect()
    }
}

fn bn_params(g: &GraphProto, bn: &NodeProto) -> Result<BnParams, String> {
    let get = |i: usize| -> Result<Vec<f32>, String> {
        let name = bn.input.get(i).ok_or("missing input")?;
        let t = initializer(g, name).ok_or_else(|| format!("parameter {name} is not constant"))?;
        let t = to_tensor(t).map_err(|e| e.to_string())?;
        t.as_f32().map(<[f32]>::to_vec).ok_or_else(|| format!("parameter {name} is not float32"))
    };
    let (gamma, beta, mean, var) = (get(1)?, get(2)?, get(3)?, get(4)?);
    if [beta.len(), mean.len(), var.len()].iter().any(|&n| n != gamma.len()) {
        return Err("parameters of different lengths".into());
    }
    let eps = attr::float(bn, "epsilon", 1e-5);
    let mut scale = Vec::with_capacity(gamma.len());
    for c in 0..gamma.len() {
        let denom = (var[c] + eps).sqrt();
        if !denom.is_normal() {
            return Err(format!("channel {c} has var + eps = {}: its scale would be infinite", var[c] + eps));
        }
        scale.push(gamma[c] / denom);
    }
    Ok(BnParams { scale, mean, beta })
}

impl Pass for FoldBn {
    fn name(&self) -> &'static str {
        "fold-bn"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let g = super::graph_mut(model)?;
        let (mut folded, mut mul_add, mut left) = (0, 0, Vec::new());
        let mut dead = HashSet::new();
        let bns: Vec<usize> = (0..g.node.len()).filter(|&i| g.node[i].op_type == "BatchNormalization" && g.node[i].domain.is_empty()).collect();
        for i in bns {
            let bn = g.node[i].clone();
            if bn.output.iter().skip(1).any(|o| !o.is_empty()) || attr::int(&bn, "training_mode", 0) != 0 {
                left.push(serde_json::json!({ "node": bn.name, "reason": "training-mode outputs" }));
                continue;
            }
            let p = match bn_params(g, &bn) {
                Ok(p) => p,
                Err(reason) => {
                    left.push(serde_json::json!({ "node": bn.name, "reason": reason }));
                    continue;
                }
            };
            let producer = {
                let graph = Graph::build(g)?;
                let single_use = graph.consumers_of(&bn.input[0]).len() == 1 && !g.output.iter().any(|o| o.name == bn.input[0]);
                graph.producer.get(bn.input[0].as_str()).copied().filter(|&c| single_use && matches!(g.node[c].op_type.as_str(), "Conv" | "ConvTranspose"))
            };
            if let Some(c) = producer {
                if fold_into_conv(g, c, &p)? && replace_value(g, &bn.output[0], &bn.input[0]) {
                    dead.insert(i);
                    folded += 1;
                    continue;
                }
            }
            if self.options.standalone_to_mul_add {
                to_mul_add(g, i, &p);
                mul_add += 1;
            } else {
                left.push(serde_json::json!({ "node": bn.name, "reason": "no conv before it" }));
            }
        }
        remove_nodes(g, &dead);
        crate::ir::rewrite::topo::sort_topologically(g)?;
        crate::ir::rewrite::dce::eliminate(g)?;
        Ok(serde_json::json!({ "folded_into_conv": folded, "to_mul_add": mul_add, "left": left }))
    }
}

/// Scales the conv's output channels and sets its bias; false if its weights are not constant.
fn fold_into_conv(g: &mut GraphProto, c: usize, p: &BnParams) -> Result<bool> {
    let conv = g.node[c].clone();
    let Some(w) = initializer(g, &conv.input[1]).and_then(|t| to_tensor(t).ok()) else { return Ok(false) };
    let Some(wv) = w.as_f32() else { return Ok(false) };
    let group = attr::int(&conv, "group", 1).max(1) as usize;
    let cout = p.scale.len();
    // Output channel of each weight element: Conv W is [Cout, Cin/g, k..]; ConvTranspose W is [Cin, Cout/g, k..].
    let per: usize = w.shape[2..].iter().product();
    let channel_of = |idx: usize| -> usize {
        if conv.op_type == "Conv" {
            idx / (w.shape[1] * per)
        } else {
            let cin = idx / (w.shape[1] * per);
            let oc_in_group = (idx / per) % w.shape[1];
            (cin / (w.shape[0] / group)) * w.shape[1] + oc_in_group
        }
    };
    if (conv.op_type == "Conv" && w.shape[0] != cout) || (conv.op_type == "ConvTranspose" && w.shape[1] * group != cout) {
        return Ok(false);
    }
    let new_w: Vec<f32> = wv.iter().enumerate().map(|(i, &v)| v * p.scale[channel_of(i)]).collect();
    let conv_bias: Option<Vec<f32>> = match conv.input.get(2).filter(|s| !s.is_empty()) {
        Some(b) => match initializer(g, b).and_then(|t| to_tensor(t).ok()).and_then(|t| t.as_f32().map(<[f32]>::to_vec)) {
            Some(v) if v.len() == cout => Some(v),
            _ => return Ok(false),
        },
        None => None,
    };
    let new_b = p.bias(conv_bias.as_deref());
    set_input_constant(g, c, 1, &Tensor::f32(w.shape.clone(), new_w), "bnfolded");
    set_input_constant(g, c, 2, &Tensor::f32(vec![cout], new_b), "bnfolded");
    Ok(true)
}

/// BN(x) = x * scale + shift, with [1, C, 1, ...] constants matching x's rank.
fn to_mul_add(g: &mut GraphProto, i: usize, p: &BnParams) {
    let bn = g.node[i].clone();
    let rank = Graph::build(g).ok().and_then(|graph| crate::ir::infer(&graph).shape(&bn.input[0]).map(|s| s.len())).unwrap_or(4);
    let mut shape = vec![1usize; rank.max(2)];
    shape[1] = p.scale.len();
    let sn = fresh_name(g, &format!("{}_scale", bn.name));
    set_initializer(g, from_tensor(&sn, &Tensor::f32(shape.clone(), p.scale.clone())));
    let bn2 = fresh_name(g, &format!("{}_shift", bn.name));
    set_initializer(g, from_tensor(&bn2, &Tensor::f32(shape, p.bias(None))));
    let mid = fresh_name(g, &format!("{}_scaled", bn.name));
    let mul = NodeProto { name: format!("{}_mul", bn.name), op_type: "Mul".into(), input: vec![bn.input[0].clone(), sn], output: vec![mid.clone()], ..Default::default() };
    let add = NodeProto { name: format!("{}_add", bn.name), op_type: "Add".into(), input: vec![mid, bn2], output: vec![bn.output[0].clone()], ..Default::default() };
    g.node[i] = mul;
    g.node.push(add); // indices stay valid during the pass; order is restored at its end
}
