//! A 2-D convolution written as a 3-D one over a unit axis: Unsqueeze, Conv, Squeeze (the
//! `narrow-convs-nchw` pass). The weights gain a unit kernel axis, the attributes a unit
//! stride, dilation and kernel and zero padding on it: the same products summed the same
//! way. An activation that alone reads the convolution moves inside the pair, so that a
//! runtime can still fuse it.

use crate::onnx::attr;
use crate::onnx::edit::{add_constant, fresh_name, initializer, only_reader, swap_initializer};
use crate::onnx::proto::{AttributeProto, GraphProto, NodeProto};
use crate::onnx::tensor_proto::to_tensor;
use crate::tensor::{DType, Tensor, TensorData};
use anyhow::{anyhow, Result};

/// Element-wise activations ONNX Runtime fuses into the convolution before them.
const FUSABLE: &[&str] = &["Relu", "LeakyRelu", "Clip", "Sigmoid", "Tanh", "HardSigmoid"];

/// The group-1 2-D convolutions of `g` with f32 weights in an initializer and fewer than
/// `below` input and output channels: (node index, input channels, output channels).
pub fn narrow(g: &GraphProto, below: usize) -> Vec<(usize, usize, usize)> {
    g.node
        .iter()
        .enumerate()
        .filter(|(_, n)| n.op_type == "Conv" && attr::int(n, "group", 1) == 1)
        .filter_map(|(i, n)| {
            let w = initializer(g, n.input.get(1)?)?;
            let (cout, cin) = (*w.dims.first()? as usize, *w.dims.get(1)? as usize);
            let plain = n.attribute.iter().all(|a| unit_axis(a).is_ok());
            (w.dims.len() == 4 && w.data_type == DType::F32.onnx_code() && plain && cin < below && cout < below).then_some((i, cin, cout))
        })
        .collect()
}

/// Rewrites node `i` of `g` (a 2-D convolution with weights in an initializer) as a 3-D one;
/// returns the activation moved inside with it, if any. `opset` is the model's default
/// opset: Unsqueeze and Squeeze take their axes as an input from 13, as an attribute before.
pub fn lift(g: &mut GraphProto, i: usize, opset: i64) -> Result<Option<String>> {
    let conv = g.node[i].clone();
    let name = if conv.name.is_empty() { "conv".to_string() } else { conv.name.clone() };
    let w = initializer(g, &conv.input[1]).ok_or_else(|| anyhow!("'{name}': weights not in an initializer"))?;
    if w.dims.len() != 4 || w.data_type != DType::F32.onnx_code() {
        return Err(anyhow!("'{name}': weights are not 4-D f32"));
    }
    let mut dims = w.dims.clone();
    dims.insert(2, 1);
    let weights = reshaped(g, &conv.input[1], &format!("{}_3d", conv.input[1]), dims)?;
    let attributes = conv.attribute.iter().map(unit_axis).collect::<Result<Vec<_>>>().map_err(|e| anyhow!("'{name}': {e}"))?;

    // An activation that is the convolution's only reader (and not a graph output's source)
    // runs on the 3-D value.
    let out = conv.output[0].clone();
    let readers: Vec<usize> = (0..g.node.len()).filter(|&j| g.node[j].input.contains(&out)).collect();
    let is_output = |v: &str| g.output.iter().any(|o| o.name == v);
    let act = match readers.as_slice() {
        [j] if *j > i && FUSABLE.contains(&g.node[*j].op_type.as_str()) && g.node[*j].input[0] == out && !is_output(&out) => Some(*j),
        _ => None,
    };

    let (axes_input, axes_attr) = if opset >= 13 {
        (Some(add_constant(g, &format!("{name}_unit_axis"), &Tensor::new(vec![1], TensorData::I64(vec![2])))), vec![])
    } else {
        (None, vec![attr::make_ints("axes", vec![2])])
    };
    let with_axes = |x: String| std::iter::once(x).chain(axes_input.clone()).collect::<Vec<_>>();
    let lifted_in = fresh_name(g, &format!("{}_3d", conv.input[0]));
    let lifted_out = fresh_name(g, &format!("{out}_3d"));
    let unsqueeze = NodeProto { name: format!("{name}_unsqueeze"), op_type: "Unsqueeze".into(), input: with_axes(conv.input[0].clone()), output: vec![lifted_in.clone()], attribute: axes_attr.clone(), ..Default::default() };
    let mut input = vec![lifted_in, weights];
    input.extend(conv.input.iter().skip(2).cloned());
    let conv3d = NodeProto { input, output: vec![lifted_out.clone()], attribute: attributes, ..conv.clone() };

    let (squeezed_from, last) = match act {
        Some(j) => {
            let final_out = g.node[j].output[0].clone();
            let act_out = fresh_name(g, &format!("{final_out}_3d"));
            retag(g, &out, &lifted_out, true);
            let a = &mut g.node[j];
            a.input[0] = lifted_out;
            a.output[0] = act_out.clone();
            (act_out, final_out)
        }
        None => (lifted_out, out),
    };
    let squeeze = NodeProto { name: format!("{name}_squeeze"), op_type: "Squeeze".into(), input: with_axes(squeezed_from), output: vec![last], attribute: axes_attr, ..Default::default() };
    let moved = act.map(|j| g.node[j].op_type.clone());
    match act {
        // The Squeeze goes after the activation, which comes later in the node order.
        Some(j) => {
            g.node.insert(j + 1, squeeze);
            g.node.splice(i..=i, [unsqueeze, conv3d]);
        }
        None => {
            g.node.splice(i..=i, [unsqueeze, conv3d, squeeze]);
        }
    }
    Ok(moved)
}

/// A 2-D convolution attribute with the unit axis put first among the spatial ones.
fn unit_axis(a: &AttributeProto) -> Result<AttributeProto> {
    let v = || a.ints.clone();
    Ok(match a.name.as_str() {
        "kernel_shape" | "strides" | "dilations" if a.ints.len() == 2 => attr::make_ints(&a.name, [vec![1], v()].concat()),
        "pads" if a.ints.len() == 4 => attr::make_ints("pads", vec![0, a.ints[0], a.ints[1], 0, a.ints[2], a.ints[3]]),
        "group" | "auto_pad" => a.clone(),
        other => return Err(anyhow!("attribute {other} {:?} is not a 2-D convolution's", a.ints)),
    })
}

/// Undoes [`lift`] wherever `g` has its form (Unsqueeze on axis 2, a 3-D convolution with a
/// unit first kernel axis, at most one activation, Squeeze on axis 2, each the only reader
/// of the one before): the 2-D convolution comes back under its own names. Returns how
/// many were lowered.
pub fn lower_all(g: &mut GraphProto) -> Result<usize> {
    let mut count = 0;
    while let Some((u, c, a, s)) = find_lifted(g) {
        let x = g.node[u].input[0].clone();
        let out = g.node[s].output[0].clone();
        let wname = g.node[c].input[1].clone();
        let mut dims = initializer(g, &wname).expect("checked by find_lifted").dims.clone();
        dims.remove(2);
        let weights = reshaped(g, &wname, wname.strip_suffix("_3d").unwrap_or(&wname), dims)?;
        let conv = &mut g.node[c];
        conv.input[0] = x;
        conv.input[1] = weights;
        conv.attribute = conv.attribute.iter().map(drop_unit_axis).collect();
        match a {
            Some(a) => {
                let lifted = g.node[c].output[0].clone();
                let mid = fresh_name(g, lifted.strip_suffix("_3d").unwrap_or(&lifted));
                retag(g, &lifted, &mid, false);
                g.node[c].output[0] = mid.clone();
                g.node[a].input[0] = mid;
                g.node[a].output[0] = out;
            }
            None => g.node[c].output[0] = out,
        }
        let dead: std::collections::HashSet<usize> = [u, s].into();
        crate::onnx::edit::remove_nodes(g, &dead);
        count += 1;
    }
    if count > 0 {
        super::dce::eliminate(g)?;
    }
    Ok(count)
}

/// Whether `g` has a convolution [`lower_all`] would lower.
pub fn any_lifted(g: &GraphProto) -> bool {
    find_lifted(g).is_some()
}

/// The first lifted convolution of `g`: (Unsqueeze, Conv, activation, Squeeze) node indices.
fn find_lifted(g: &GraphProto) -> Option<(usize, usize, Option<usize>, usize)> {
    let only_reader = |v: &str| only_reader(g, v);
    let on_axis_2 = |n: &NodeProto| {
        let axes = match n.input.get(1) {
            Some(a) => initializer(g, a).and_then(|t| to_tensor(t).ok()).and_then(|t| t.as_i64s()),
            None => attr::ints(n, "axes"),
        };
        axes.as_deref() == Some(&[2])
    };
    (0..g.node.len()).find_map(|u| {
        let un = &g.node[u];
        if un.op_type != "Unsqueeze" || !on_axis_2(un) {
            return None;
        }
        let c = only_reader(&un.output[0])?;
        let cn = &g.node[c];
        let w = initializer(g, cn.input.get(1)?)?;
        // Each spatial attribute has the unit axis first: 1 for the kernel, stride and
        // dilation, no padding on either side.
        let unit = |name: &str| {
            attr::ints(cn, name).is_none_or(|v| match name {
                "pads" => v.len() == 6 && v[0] == 0 && v[3] == 0,
                _ => v.len() == 3 && v[0] == 1,
            })
        };
        let plain = cn.op_type == "Conv" && cn.input[0] == un.output[0] && w.dims.len() == 5 && w.dims[2] == 1 && w.data_type == DType::F32.onnx_code()
            && ["kernel_shape", "strides", "dilations", "pads"].iter().all(|a| unit(a));
        if !plain {
            return None;
        }
        let next = only_reader(&cn.output[0])?;
        let (a, s) = match g.node[next].op_type.as_str() {
            "Squeeze" => (None, next),
            op if FUSABLE.contains(&op) && g.node[next].input[0] == cn.output[0] => (Some(next), only_reader(&g.node[next].output[0])?),
            _ => return None,
        };
        (g.node[s].op_type == "Squeeze" && on_axis_2(&g.node[s])).then_some((u, c, a, s))
    })
}

/// A 3-D convolution attribute from [`unit_axis`] back in 2-D.
fn drop_unit_axis(a: &AttributeProto) -> AttributeProto {
    match a.name.as_str() {
        "kernel_shape" | "strides" | "dilations" => attr::make_ints(&a.name, a.ints[1..].to_vec()),
        "pads" => attr::make_ints("pads", vec![a.ints[1], a.ints[2], a.ints[4], a.ints[5]]),
        _ => a.clone(),
    }
}

/// The weights `name` under the new shape `dims` (the same values), called `base` or a fresh
/// name from it: renamed where they lie when no other node reads them, so that lifting and
/// lowering give back the same model, byte for byte; copied otherwise.
fn reshaped(g: &mut GraphProto, name: &str, base: &str, dims: Vec<i64>) -> Result<String> {
    let mut t = initializer(g, name).ok_or_else(|| anyhow!("no initializer '{name}'"))?.clone();
    t.dims = dims;
    Ok(swap_initializer(g, name, base, t))
}

/// Renames the value_info of `from` (a convolution's output that [`lift`] or [`lower_all`]
/// renames) to `to`, its shape gaining (`unit`) or losing the unit axis 2.
fn retag(g: &mut GraphProto, from: &str, to: &str, unit: bool) {
    use crate::onnx::proto::{Dimension, DimensionValue, TypeValue};
    for v in g.value_info.iter_mut().filter(|v| v.name == from) {
        v.name = to.to_string();
        if let Some(TypeValue::TensorType(t)) = v.r#type.as_mut().and_then(|t| t.value.as_mut()) {
            if let Some(shape) = t.shape.as_mut() {
                match unit {
                    true if shape.dim.len() == 4 => shape.dim.insert(2, Dimension { value: Some(DimensionValue::DimValue(1)), denotation: String::new() }),
                    false if shape.dim.len() == 5 => drop(shape.dim.remove(2)),
                    _ => {}
                }
            }
        }
    }
}
