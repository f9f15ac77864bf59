//! A 2-D convolution whose bias is read through a DequantizeLinear (the `bias` form of
//! `narrow-convs-nchw`): int32 codes of 1 and the bias itself as the per-channel scale, so the
//! value is the bias exactly (each element a product by 1). ONNX Runtime's NCHWc transform
//! (x86) takes a convolution only when its bias is a constant, and its constant folding leaves
//! DequantizeLinear nodes alone (it keeps QDQ units whole), so the convolution stays 2-D on
//! the NCHW kernels: neither the blocked kernel with its output padded to 16 channels nor the
//! 3-D form's generic im2col. A convolution without a bias gets one of zeros. [`unpin_all`]
//! gives every constant bias back, byte for byte.

use crate::onnx::attr;
use crate::onnx::edit::{add_constant, fresh_name, initializer, only_reader, remove_nodes};
use crate::onnx::proto::{GraphProto, NodeProto};
use crate::onnx::tensor_proto::to_tensor;
use crate::tensor::{DType, Tensor, TensorData};
use anyhow::{anyhow, bail, Result};

/// Name tags of the DequantizeLinear: reading the convolution's own bias, or a bias of zeros
/// added where it had none (which [`unpin_all`] drops again).
const OWN: &str = "_bias_pin";
const ADDED: &str = "_added_bias_pin";

/// Routes the bias of node `i` (a convolution with f32 weights in an initializer) through a
/// DequantizeLinear. Needs opset 13 (a per-channel DequantizeLinear).
pub fn pin(g: &mut GraphProto, i: usize) -> Result<()> {
    let conv = g.node[i].clone();
    let name = if conv.name.is_empty() { "conv".to_string() } else { conv.name.clone() };
    let w = initializer(g, &conv.input[1]).ok_or_else(|| anyhow!("'{name}': weights not in an initializer"))?;
    let cout = *w.dims.first().ok_or_else(|| anyhow!("'{name}': weights without dimensions"))? as usize;
    let (scale, tag) = match conv.input.get(2).filter(|b| !b.is_empty()) {
        Some(b) => {
            let t = initializer(g, b).ok_or_else(|| anyhow!("'{name}': bias not in an initializer"))?;
            if t.data_type != DType::F32.onnx_code() || t.dims != [cout as i64] {
                bail!("'{name}': bias is not {cout} f32 values");
            }
            (b.clone(), OWN)
        }
        None => (add_constant(g, &format!("{name}_bias"), &Tensor::new(vec![cout], TensorData::F32(vec![0.0; cout]))), ADDED),
    };
    let codes = add_constant(g, &format!("{name}_bias_codes"), &Tensor::new(vec![cout], TensorData::I32(vec![1; cout])));
    let out = fresh_name(g, &format!("{name}_pinned_bias"));
    let dq = NodeProto {
        name: format!("{name}{tag}"),
        op_type: "DequantizeLinear".into(),
        input: vec![codes, scale],
        output: vec![out.clone()],
        attribute: vec![attr::make_int("axis", 0)],
        ..Default::default()
    };
    let c = &mut g.node[i];
    if c.input.len() < 3 {
        c.input.resize(3, String::new());
    }
    c.input[2] = out;
    g.node.insert(i, dq);
    Ok(())
}

/// Undoes [`pin`] wherever `g` has its form; returns how many biases came back.
pub fn unpin_all(g: &mut GraphProto) -> Result<usize> {
    let found: Vec<(usize, usize, bool)> = (0..g.node.len()).filter_map(|d| pinned(g, d).map(|(c, added)| (d, c, added))).collect();
    for &(d, c, added) in &found {
        let scale = g.node[d].input[1].clone();
        let conv = &mut g.node[c];
        if added {
            conv.input.truncate(2);
        } else {
            conv.input[2] = scale;
        }
    }
    if !found.is_empty() {
        remove_nodes(g, &found.iter().map(|f| f.0).collect());
        super::dce::eliminate(g)?;
    }
    Ok(found.len())
}

/// Whether `g` has a bias [`unpin_all`] would give back.
pub fn any_pinned(g: &GraphProto) -> bool {
    (0..g.node.len()).any(|d| pinned(g, d).is_some())
}

/// Node `d` as [`pin`] writes it: (the convolution it feeds, whether its bias was added).
fn pinned(g: &GraphProto, d: usize) -> Option<(usize, bool)> {
    let n = &g.node[d];
    let added = n.name.ends_with(ADDED);
    if n.op_type != "DequantizeLinear" || !(added || n.name.ends_with(OWN)) || n.input.len() != 2 || attr::int(n, "axis", 1) != 0 {
        return None;
    }
    let codes = to_tensor(initializer(g, &n.input[0])?).ok()?;
    let scale = to_tensor(initializer(g, &n.input[1])?).ok()?;
    let ones = matches!(&codes.data, TensorData::I32(v) if v.iter().all(|&x| x == 1));
    let zeros = matches!(&scale.data, TensorData::F32(v) if v.iter().all(|&x| x == 0.0));
    if !ones || codes.shape != scale.shape || codes.shape.len() != 1 || (added && !zeros) || !matches!(scale.data, TensorData::F32(_)) {
        return None;
    }
    let c = only_reader(g, &n.output[0])?;
    (g.node[c].op_type == "Conv" && g.node[c].input.get(2) == Some(&n.output[0])).then_some((c, added))
}
