//! QDQ emission: QuantizeLinear/DequantizeLinear pairs around the planned values, int8
//! per-channel weights and int32 biases behind DequantizeLinear. ONNX Runtime fuses
//! DQ -> op -> Q into its integer kernels (QLinearConv, QLinearAdd, ...); any other runtime
//! reads the same file as float arithmetic on quantized values.

use super::params::{quantize_bias, quantize_weights, ActivationType, QParams, QuantizedWeights};
use super::plan::Plan;
use crate::ir::Graph;
use crate::onnx::edit::{fresh_name, set_initializer};
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::{AttributeProto, GraphProto, ModelProto, NodeProto};
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Result};
use std::collections::{BTreeMap, HashMap};

/// What emission needs beyond the plan.
pub struct EmitOptions<'a> {
    /// Parameters of every quantized value (after `Plan::root`).
    pub params: &'a HashMap<String, QParams>,
    pub activations: ActivationType,
    pub weight_bits: u32,
    /// Per-channel bias shifts measured by bias correction, by node index (subtracted).
    pub bias_shift: &'a HashMap<usize, Vec<f64>>,
    /// Learned integer weights by node index (learned rounding); others round to nearest.
    pub weights: &'a HashMap<usize, QuantizedWeights>,
}

#[derive(Default, Debug, serde::Serialize)]
pub struct Emitted {
    /// Quantized value -> the name of its dequantized copy in the emitted graph.
    #[serde(skip)]
    pub dequantized: BTreeMap<String, String>,
    pub quantized_values: usize,
    pub quantized_nodes: usize,
    pub int8_weights: usize,
    /// Biases whose int32 value had to be clamped (a tiny input or weight scale).
    pub biases_clamped: usize,
    /// Relus removed because their output quantization clamps at zero (`Plan::fused_relu`).
    pub relus_fused: usize,
    /// Nodes computed on the integer codes (`plan::ON_CODES`).
    pub on_codes: usize,
}

/// The QDQ model for `model` under `plan`.
pub fn emit(model: &ModelProto, plan: &Plan, o: &EmitOptions) -> Result<(ModelProto, Emitted)> {
    let opset = crate::onnx::edit::default_opset(model).unwrap_or(0);
    if opset < 13 {
        bail!("quantization needs opset 13 or newer (per-channel DequantizeLinear); the model has opset {opset}; re-export it with opset_version=13 or later");
    }
    let src = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let graph = Graph::build(src)?;
    let mut g: GraphProto = src.clone();
    let mut stats = Emitted::default();
    let param = |v: &str| -> Result<QParams> { o.params.get(plan.root(v)).copied().ok_or_else(|| anyhow!("no calibrated range for '{v}'")) };

    // Activations: one Q/DQ pair per value.
    for v in plan.quantized_values(&graph) {
        let p = param(&v)?;
        let dq = add_qdq(&mut g, &v, &p, o.activations);
        let all_readers = plan.produced_quantized(&graph, &v);
        for &c in graph.consumers_of(&v) {
            let slots = if all_readers { (0..src.node[c].input.len()).collect() } else if plan.quantized.contains(&c) { Plan::activation_slots(&graph, c) } else { vec![] };
            for s in slots {
                if g.node[c].input[s] == v {
                    g.node[c].input[s] = dq.clone();
                }
            }
        }
        stats.dequantized.insert(v, dq);
        stats.quantized_values += 1;
    }

    // Constant operands of quantized arithmetic (gate maps, added constants): per-tensor.
    let mut constants: HashMap<String, String> = HashMap::new();
    for &i in &plan.quantized {
        for s in Plan::activation_slots(&graph, i) {
            let name = src.node[i].input[s].clone();
            let Some(t) = graph.initializers.get(name.as_str()) else { continue };
            if !constants.contains_key(&name) {
                let t = to_tensor(t)?;
                let v = t.as_f32().expect("planned constants are f32");
                let p = QParams::covering(v, o.activations);
                let q = quantized_tensor(&t.shape, v.iter().map(|&x| p.quantize(x as f64)), o.activations);
                let qname = fresh_name(&g, &format!("{name}_quantized"));
                set_initializer(&mut g, from_tensor(&qname, &q));
                let dq = dequantize(&mut g, &qname, &p, o.activations);
                constants.insert(name.clone(), dq);
            }
            g.node[i].input[s] = constants[&name].clone();
        }
    }

    // Convolution weights and biases.
    for &i in &plan.quantized {
        let n = &src.node[i];
        if n.op_type != "Conv" {
            continue;
        }
        let w = to_tensor(graph.initializers[n.input[1].as_str()])?;
        let out_channels = w.shape[0];
        let qw = match o.weights.get(&i) {
            Some(learned) => learned.clone(),
            None => quantize_weights(w.as_f32().expect("planned"), out_channels, o.weight_bits),
        };
        let w_name = fresh_name(&g, &format!("{}_int8", n.input[1]));
        set_initializer(&mut g, from_tensor(&w_name, &Tensor::new(w.shape.clone(), TensorData::I8(qw.values))));
        let w_dq = dequantize_per_channel(&mut g, &w_name, &qw.scales, TensorData::I8(vec![0; out_channels]), 0);
        g.node[i].input[1] = w_dq;
        stats.int8_weights += w.len();

        let mut bias: Vec<f64> = match n.input.get(2).filter(|s| !s.is_empty()) {
            Some(b) => to_tensor(graph.initializers[b.as_str()])?.data.to_f64(),
            None => vec![0.0; out_channels],
        };
        if let Some(shift) = o.bias_shift.get(&i) {
            for (b, s) in bias.iter_mut().zip(shift) {
                *b -= s;
            }
        }
        let s_in = param(&n.input[0])?.scale;
        let bias32: Vec<f32> = bias.iter().map(|&b| b as f32).collect();
        let (values, scales, clamped) = quantize_bias(&bias32, s_in, &qw.scales);
        stats.biases_clamped += clamped;
        let b_name = fresh_name(&g, &format!("{}_bias_int32", if n.name.is_empty() { "conv" } else { &n.name }));
        set_initializer(&mut g, from_tensor(&b_name, &Tensor::new(vec![out_channels], TensorData::I32(values))));
        let b_dq = dequantize_per_channel(&mut g, &b_name, &scales, TensorData::I32(vec![0; out_channels]), 0);
        let node = &mut g.node[i];
        if node.input.len() < 3 {
            node.input.resize(3, String::new());
        }
        node.input[2] = b_dq;
    }
    let (on_codes, mut dead) = on_codes(&mut g, plan, src);
    stats.on_codes = on_codes;
    // Fused Relus: the output's QuantizeLinear reads the Relu's input instead. Exact when its
    // zero point is the lowest code (always, as ranges start at 0), since the quantizer then
    // clamps negatives to zero itself.
    for (x, &r) in &plan.fused_relu {
        let y = &src.node[r].output[0];
        let p = param(y)?;
        if p.zero_point != p.qmin {
            continue;
        }
        for n in g.node.iter_mut().filter(|n| n.op_type == "QuantizeLinear" && n.input[0] == *y) {
            n.input[0] = x.clone();
        }
        dead.insert(r);
        stats.relus_fused += 1;
    }
    crate::onnx::edit::remove_nodes(&mut g, &dead);
    stats.quantized_nodes = plan.quantized.len();
    sort_topologically(&mut g)?;
    let mut out = model.clone();
    out.graph = Some(g);
    Ok((out, stats))
}

/// Makes each quantized node of `plan::ON_CODES` read its inputs' integer codes and write its
/// output's (exact: they share one scale and zero point), in place of the DequantizeLinear
/// before it and the QuantizeLinear after it. Returns how many, and the QuantizeLinear nodes
/// to remove (a DequantizeLinear left unread stays for the analyses that read it; the pass's
/// final dead-code elimination removes it).
fn on_codes(g: &mut GraphProto, plan: &Plan, src: &GraphProto) -> (usize, std::collections::HashSet<usize>) {
    let (mut count, mut dead) = (0, std::collections::HashSet::new());
    let dequantizer = |g: &GraphProto, v: &str| g.node.iter().position(|n| n.op_type == "DequantizeLinear" && n.output.first().map(String::as_str) == Some(v));
    for &i in plan.quantized.iter().filter(|&&i| super::plan::ON_CODES.contains(&src.node[i].op_type.as_str()) && !plan.float_output.contains(&i)) {
        let y = g.node[i].output[0].clone();
        let dqs: Option<Vec<usize>> = g.node[i].input.iter().map(|v| dequantizer(g, v)).collect();
        let qs: Vec<usize> = (0..g.node.len()).filter(|&j| g.node[j].op_type == "QuantizeLinear" && g.node[j].input[0] == y).collect();
        let (Some(dqs), [q]) = (dqs, qs.as_slice()) else { continue };
        g.node[i].input = dqs.iter().map(|&d| g.node[d].input[0].clone()).collect();
        g.node[i].output[0] = g.node[*q].output[0].clone();
        dead.insert(*q);
        count += 1;
    }
    (count, dead)
}

/// Adds QuantizeLinear(v) -> DequantizeLinear and returns the dequantized value's name.
pub fn add_qdq(g: &mut GraphProto, v: &str, p: &QParams, ty: ActivationType) -> String {
    let (scale, zp) = scalar_params(g, v, p, ty);
    let q = fresh_name(g, &format!("{v}_q"));
    let dq = fresh_name(g, &format!("{v}_dq"));
    g.node.push(node("QuantizeLinear", &format!("{v}_quantize"), vec![v.to_string(), scale.clone(), zp.clone()], vec![q.clone()], vec![]));
    g.node.push(node("DequantizeLinear", &format!("{v}_dequantize"), vec![q, scale, zp], vec![dq.clone()], vec![]));
    dq
}

fn dequantize(g: &mut GraphProto, q: &str, p: &QParams, ty: ActivationType) -> String {
    let (scale, zp) = scalar_params(g, q, p, ty);
    let dq = fresh_name(g, &format!("{q}_dq"));
    g.node.push(node("DequantizeLinear", &format!("{q}_dequantize"), vec![q.to_string(), scale, zp], vec![dq.clone()], vec![]));
    dq
}

pub(crate) fn dequantize_per_channel(g: &mut GraphProto, q: &str, scales: &[f64], zero_points: TensorData, axis: i64) -> String {
    let s = fresh_name(g, &format!("{q}_scale"));
    set_initializer(g, from_tensor(&s, &Tensor::f32(vec![scales.len()], scales.iter().map(|&x| x as f32).collect())));
    let z = fresh_name(g, &format!("{q}_zero_point"));
    set_initializer(g, from_tensor(&z, &Tensor::new(vec![scales.len()], zero_points)));
    let dq = fresh_name(g, &format!("{q}_dq"));
    let axis = AttributeProto { name: "axis".into(), i: Some(axis), r#type: 2, ..Default::default() };
    g.node.push(node("DequantizeLinear", &format!("{q}_dequantize"), vec![q.to_string(), s, z], vec![dq.clone()], vec![axis]));
    dq
}

fn scalar_params(g: &mut GraphProto, v: &str, p: &QParams, ty: ActivationType) -> (String, String) {
    let scale = fresh_name(g, &format!("{v}_scale"));
    set_initializer(g, from_tensor(&scale, &Tensor::f32(vec![], vec![p.scale as f32])));
    let zp = fresh_name(g, &format!("{v}_zero_point"));
    set_initializer(g, from_tensor(&zp, &quantized_tensor(&[], std::iter::once(p.zero_point), ty)));
    (scale, zp)
}

pub fn quantized_tensor(shape: &[usize], values: impl Iterator<Item = i32>, ty: ActivationType) -> Tensor {
    let data = match ty {
        ActivationType::U8 => TensorData::U8(values.map(|v| v as u8).collect()),
        ActivationType::I8 => TensorData::I8(values.map(|v| v as i8).collect()),
    };
    Tensor::new(shape.to_vec(), data)
}

pub fn node(op: &str, name: &str, input: Vec<String>, output: Vec<String>, attribute: Vec<AttributeProto>) -> NodeProto {
    NodeProto { op_type: op.into(), name: name.into(), input, output, attribute, ..Default::default() }
}
