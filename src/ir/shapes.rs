//! Dtype and static-shape inference for the ops `torch.onnx.export` emits for PDI-Net.
//!
//! PyTorch computes many shapes at run time (Shape -> Gather -> Unsqueeze -> Concat ->
//! Reshape), so inference carries small integer constants along and evaluates those chains.
//! An op it does not know keeps whatever `value_info` declares and is named in a warning:
//! a guessed shape would be worse than none.

use super::graph::Graph;
use crate::onnx::attr;
use crate::onnx::proto::{DimensionValue, NodeProto, TypeValue, ValueInfoProto};
use crate::onnx::tensor_proto::to_tensor;
use crate::tensor::{DType, Tensor, TensorData};
use std::collections::{BTreeSet, HashMap};

/// Constants bigger than this are not carried: shape arithmetic never needs them.
const MAX_CONST_ELEMS: usize = 64;

#[derive(Clone, Debug, PartialEq, Default)]
pub struct ValueType {
    pub dtype: Option<DType>,
    /// Dimensions, `-1` where unknown; `None` when even the rank is unknown.
    pub shape: Option<Vec<i64>>,
}

impl ValueType {
    pub fn static_shape(&self) -> Option<Vec<usize>> {
        let s = self.shape.as_ref()?;
        s.iter().all(|&d| d >= 0).then(|| s.iter().map(|&d| d as usize).collect())
    }
}

pub struct Inferred {
    pub types: HashMap<String, ValueType>,
    /// Small constants found on the way (shape chains, scales).
    pub consts: HashMap<String, Tensor>,
    pub warnings: Vec<String>,
}

impl Inferred {
    pub fn shape(&self, v: &str) -> Option<Vec<usize>> {
        self.types.get(v).and_then(|t| t.static_shape())
    }
}

pub fn declared(v: &ValueInfoProto) -> ValueType {
    let Some(TypeValue::TensorType(t)) = v.r#type.as_ref().and_then(|t| t.value.as_ref()) else { return ValueType::default() };
    ValueType {
        dtype: DType::from_onnx(t.elem_type),
        shape: t.shape.as_ref().map(|s| {
            s.dim.iter().map(|d| match d.value { Some(DimensionValue::DimValue(x)) => x, _ => -1 }).collect()
        }),
    }
}

pub fn infer(g: &Graph) -> Inferred {
    let mut cx = Inferred { types: HashMap::new(), consts: HashMap::new(), warnings: Vec::new() };
    for v in g.proto.input.iter().chain(&g.proto.value_info).chain(&g.proto.output) {
        cx.types.insert(v.name.clone(), declared(v));
    }
    for (name, t) in &g.initializers {
        cx.types.insert(name.to_string(), ValueType { dtype: DType::from_onnx(t.data_type), shape: Some(t.dims.clone()) });
        if product(&t.dims).is_some_and(|n| n <= MAX_CONST_ELEMS as i64) {
            if let Ok(c) = to_tensor(t) {
                cx.consts.insert(name.to_string(), c);
            }
        }
    }
    let mut unknown_ops = BTreeSet::new();
    for &i in &g.order {
        let node = g.node(i);
        let known = infer_node(node, &mut cx);
        if !known && node.domain.is_empty() {
            unknown_ops.insert(node.op_type.clone());
        } else if !known {
            unknown_ops.insert(format!("{}:{}", node.domain, node.op_type));
        }
    }
    for op in unknown_ops {
        cx.warnings.push(format!("shape inference does not know op {op}: its outputs keep the shapes value_info declares"));
    }
    cx
}

/// Sets the outputs of `node`; false if the op is unknown (declared shapes are left alone).
fn infer_node(node: &NodeProto, cx: &mut Inferred) -> bool {
    let inp = |i: usize| -> ValueType {
        node.input.get(i).filter(|s| !s.is_empty()).and_then(|s| cx.types.get(s)).cloned().unwrap_or_default()
    };
    let ints = |i: usize| -> Option<Vec<i64>> {
        node.input.get(i).filter(|s| !s.is_empty()).and_then(|s| cx.consts.get(s)).and_then(|t| t.as_i64s())
    };
    let x = inp(0);
    let same = |dt: Option<DType>| vec![ValueType { dtype: dt, shape: x.shape.clone() }];
    let op = node.op_type.as_str();
    let outs: Vec<ValueType> = match (node.domain.as_str(), op) {
        ("" | "ai.onnx", _) => match op {
            "Identity" | "Relu" | "Sigmoid" | "Tanh" | "LeakyRelu" | "Elu" | "Selu" | "HardSigmoid" | "HardSwish"
            | "Softplus" | "Softsign" | "Exp" | "Log" | "Sqrt" | "Neg" | "Abs" | "Erf" | "Floor" | "Ceil" | "Round"
            | "Reciprocal" | "Sign" | "Sin" | "Cos" | "Mish" | "Gelu" | "Clip" | "Softmax" | "LogSoftmax"
            | "InstanceNormalization" | "LayerNormalization" | "LRN" | "PRelu" | "Celu" | "ThresholdedRelu"
            | "BatchNormalization" | "Dropout" | "Not" | "CumSum" | "Hardmax" => same(x.dtype),
            "IsNaN" | "IsInf" => same(Some(DType::Bool)),
            "Cast" => same(DType::from_onnx(attr::int(node, "to", 0) as i32)),
            "CastLike" => same(inp(1).dtype),
            "QuantizeLinear" => same(inp(2).dtype.or(Some(DType::U8))),
            "DequantizeLinear" => same(inp(1).dtype.or(Some(DType::F32))),
            "Add" | "Sub" | "Mul" | "Div" | "Pow" | "Max" | "Min" | "Mod" | "Sum" | "Mean" | "BitShift" => {
                let all: Vec<ValueType> = (0..node.input.len()).map(inp).collect();
                vec![ValueType { dtype: x.dtype, shape: broadcast_all(&all) }]
            }
            "Equal" | "Less" | "Greater" | "LessOrEqual" | "GreaterOrEqual" | "And" | "Or" | "Xor" => {
                vec![ValueType { dtype: Some(DType::Bool), shape: broadcast_all(&[inp(0), inp(1)]) }]
            }
            "Where" => vec![ValueType { dtype: inp(1).dtype, shape: broadcast_all(&[inp(0), inp(1), inp(2)]) }],
            "Conv" | "ConvInteger" | "QLinearConv" => vec![conv(node, &x, &inp(if op == "QLinearConv" { 3 } else { 1 }), op)],
            "ConvTranspose" => vec![conv_transpose(node, &x, &inp(1))],
            "MaxPool" | "AveragePool" | "LpPool" => vec![pool(node, &x); node.output.len().max(1)],
            "GlobalAveragePool" | "GlobalMaxPool" => {
                same(x.dtype).into_iter().map(|mut t| { if let Some(s) = &mut t.shape { for d in s.iter_mut().skip(2) { *d = 1 } } t }).collect()
            }
            "Concat" => vec![concat(node, &(0..node.input.len()).map(inp).collect::<Vec<_>>())],
            "Split" => split(node, &x, ints(1)),
            "Slice" => vec![slice(node, &x, ints(1), ints(2), ints(3), ints(4))],
            "Reshape" => vec![ValueType { dtype: x.dtype, shape: ints(1).and_then(|s| reshape(&x, &s, attr::int(node, "allowzero", 0) != 0)) }],
            "Transpose" => vec![transpose(node, &x)],
            "Resize" | "Upsample" => vec![resize(node, &x, cx)],
            "Flatten" => vec![flatten(node, &x)],
            "Gemm" => vec![gemm(node, &x, &inp(1))],
            "MatMul" | "MatMulInteger" => vec![matmul(&x, &inp(1), op)],
            "ReduceMean" | "ReduceSum" | "ReduceMax" | "ReduceMin" | "ReduceProd" | "ReduceL1" | "ReduceL2" | "ReduceSumSquare"
            | "ReduceLogSumExp" => vec![reduce(node, &x, ints(1))],
            "ArgMax" | "ArgMin" => {
                let mut t = reduce_axes(node, &x, Some(vec![attr::int(node, "axis", 0)]));
                t.dtype = Some(DType::I64);
                vec![t]
            }
            "Shape" => vec![shape_op(node, &x, cx)],
            "Size" => vec![ValueType { dtype: Some(DType::I64), shape: Some(vec![]) }],
            "Gather" => vec![gather(node, &x, &inp(1), cx)],
            "Unsqueeze" => vec![unsqueeze(node, &x, ints(1), cx)],
            "Squeeze" => vec![squeeze(node, &x, ints(1), cx)],
            "Constant" => vec![constant(node, cx)],
            "ConstantOfShape" => vec![constant_of_shape(node, ints(0), cx)],
            "Expand" => vec![ValueType { dtype: x.dtype, shape: ints(1).and_then(|s| broadcast(x.shape.as_ref()?, &s)) }],
            "Tile" => vec![ValueType { dtype: x.dtype, shape: x.shape.as_ref().zip(ints(1)).map(|(s, r)| s.iter().zip(&r).map(|(&a, &b)| if a < 0 { -1 } else { a.saturating_mul(b) }).collect()) }],
            "Pad" => vec![pad(node, &x, ints(1))],
            "Range" => vec![range(node, cx)],
            "DepthToSpace" | "SpaceToDepth" => vec![depth_space(node, &x)],
            _ => return false,
        },
        _ => return false,
    };
    fold_int_consts(node, cx);
    for (name, t) in node.output.iter().zip(outs) {
        if name.is_empty() {
            continue;
        }
        // Keep what value_info declared where inference knows less.
        let entry = cx.types.entry(name.clone()).or_default();
        if t.dtype.is_some() {
            entry.dtype = t.dtype;
        }
        if t.shape.is_some() {
            entry.shape = t.shape;
        }
    }
    true
}

/// `a` as an index into `rank` dimensions (negative counts from the end); None when out of range.
fn norm_axis(a: i64, rank: usize) -> Option<usize> {
    let a = if a < 0 { a + rank as i64 } else { a };
    (0..rank as i64).contains(&a).then_some(a as usize)
}

fn broadcast(a: &[i64], b: &[i64]) -> Option<Vec<i64>> {
    let r = a.len().max(b.len());
    let get = |s: &[i64], i: usize| if i + s.len() >= r { s[i + s.len() - r] } else { 1 };
    (0..r)
        .map(|i| {
            let (x, y) = (get(a, i), get(b, i));
            Some(match (x, y) {
                (1, y) => y,
                (x, 1) => x,
                (x, y) if x == y => x,
                (-1, y) | (y, -1) => y.max(-1),
                _ => return None,
            })
        })
        .collect()
}

fn broadcast_all(ts: &[ValueType]) -> Option<Vec<i64>> {
    let mut acc: Vec<i64> = Vec::new();
    for t in ts {
        acc = broadcast(&acc, t.shape.as_ref()?)?;
    }
    Some(acc)
}

/// The product of known dims; None when one is unknown or the product overflows (untrusted
/// files carry any dims; a wrapped product would be a wrong shape, not an error).
pub(crate) fn product(dims: &[i64]) -> Option<i64> {
    dims.iter().try_fold(1i64, |a, &d| if d < 0 { None } else { a.checked_mul(d) })
}

fn spatial_out(inp: i64, k: i64, stride: i64, dil: i64, pad: i64, ceil: bool) -> i64 {
    if inp < 0 || stride <= 0 {
        return -1;
    }
    (|| {
        let eff = k.checked_sub(1)?.checked_mul(dil)?.checked_add(1)?;
        let num = inp.checked_add(pad)?.checked_sub(eff)?;
        if num < 0 {
            return Some(0);
        }
        let mut o = if ceil { num.checked_add(stride - 1)? / stride + 1 } else { num / stride + 1 };
        // ONNX/PyTorch rule: the last window must start inside the input or left padding.
        if ceil && (o - 1).checked_mul(stride)? >= inp.checked_add(pad / 2)? {
            o -= 1;
        }
        Some(o)
    })()
    .unwrap_or(-1)
}

fn window_out(node: &NodeProto, x: &[i64], kernel: &[i64], ceil: bool) -> Vec<i64> {
    let n = kernel.len();
    let strides = attr::ints(node, "strides").unwrap_or_else(|| vec![1; n]);
    let dils = attr::ints(node, "dilations").unwrap_or_else(|| vec![1; n]);
    let pads = attr::ints(node, "pads").unwrap_or_else(|| vec![0; 2 * n]);
    let auto = attr::string(node, "auto_pad", "NOTSET");
    (0..n)
        .map(|i| {
            let inp = x.get(2 + i).copied().unwrap_or(-1);
            let s = strides.get(i).copied().unwrap_or(1).max(1);
            match auto.as_str() {
                "SAME_UPPER" | "SAME_LOWER" => if inp < 0 { -1 } else { (inp + s - 1) / s },
                "VALID" => spatial_out(inp, kernel[i], s, dils.get(i).copied().unwrap_or(1), 0, false),
                _ => spatial_out(inp, kernel[i], s, dils.get(i).copied().unwrap_or(1), pads.get(i).copied().unwrap_or(0) + pads.get(i + n).copied().unwrap_or(0), ceil),
            }
        })
        .collect()
}

fn conv(node: &NodeProto, x: &ValueType, w: &ValueType, op: &str) -> ValueType {
    let dtype = match op { "Conv" => x.dtype, "ConvInteger" => Some(DType::I32), _ => None };
    let shape = (|| {
        let xs = x.shape.as_ref().filter(|s| s.len() >= 3)?;
        let ws = w.shape.as_ref().filter(|s| s.len() == xs.len())?;
        let kernel = attr::ints(node, "kernel_shape").unwrap_or_else(|| ws[2..].to_vec());
        if kernel.len() != xs.len() - 2 {
            return None;
        }
        let mut out = vec![xs[0], ws[0]];
        out.extend(window_out(node, xs, &kernel, false));
        Some(out)
    })();
    ValueType { dtype, shape }
}

fn conv_transpose(node: &NodeProto, x: &ValueType, w: &ValueType) -> ValueType {
    let shape = (|| {
        let xs = x.shape.as_ref().filter(|s| s.len() >= 3)?;
        let ws = w.shape.as_ref().filter(|s| s.len() == xs.len())?;
        let n = ws.len().checked_sub(2)?;
        let group = attr::int(node, "group", 1);
        let mut out = vec![xs[0], ws[1].checked_mul(group).unwrap_or(-1)];
        if let Some(os) = attr::ints(node, "output_shape") {
            out.extend(os.iter().skip(os.len().saturating_sub(n)));
            return Some(out);
        }
        let k = attr::ints(node, "kernel_shape").unwrap_or_else(|| ws[2..].to_vec());
        let s = attr::ints(node, "strides").unwrap_or_else(|| vec![1; n]);
        let d = attr::ints(node, "dilations").unwrap_or_else(|| vec![1; n]);
        let p = attr::ints(node, "pads").unwrap_or_else(|| vec![0; 2 * n]);
        let op = attr::ints(node, "output_padding").unwrap_or_else(|| vec![0; n]);
        if k.len() < n || s.len() < n || d.len() < n || p.len() < 2 * n || op.len() < n {
            return None;
        }
        let auto = attr::string(node, "auto_pad", "NOTSET");
        for i in 0..n {
            let inp = *xs.get(2 + i)?;
            out.push(if inp < 0 {
                -1
            } else if auto.starts_with("SAME") {
                inp.checked_mul(s[i]).unwrap_or(-1)
            } else {
                (|| s[i].checked_mul(inp - 1)?.checked_add(op[i])?.checked_add((k[i].checked_sub(1)?).checked_mul(d[i])?)?.checked_add(1)?.checked_sub(p[i])?.checked_sub(p[i + n]))().unwrap_or(-1)
            });
        }
        Some(out)
    })();
    ValueType { dtype: x.dtype, shape }
}

fn pool(node: &NodeProto, x: &ValueType) -> ValueType {
    let shape = x.shape.as_ref().and_then(|xs| {
        let k = attr::ints(node, "kernel_shape")?;
        let mut out = xs[..2.min(xs.len())].to_vec();
        out.extend(window_out(node, xs, &k, attr::int(node, "ceil_mode", 0) != 0));
        Some(out)
    });
    ValueType { dtype: x.dtype, shape }
}

fn concat(node: &NodeProto, ins: &[ValueType]) -> ValueType {
    let dtype = ins.iter().find_map(|t| t.dtype);
    let shape = (|| {
        let first = ins.first()?.shape.clone()?;
        let axis = norm_axis(attr::int(node, "axis", 0), first.len())?;
        let mut out = first;
        out[axis] = 0;
        for t in ins {
            let d = *t.shape.as_ref()?.get(axis)?;
            out[axis] = if d < 0 || out[axis] < 0 { -1 } else { out[axis].checked_add(d).unwrap_or(-1) };
        }
        Some(out)
    })();
    ValueType { dtype, shape }
}

fn split(node: &NodeProto, x: &ValueType, split_input: Option<Vec<i64>>) -> Vec<ValueType> {
    let n = node.output.len();
    let Some(xs) = x.shape.as_ref() else { return vec![ValueType { dtype: x.dtype, shape: None }; n] };
    let Some(axis) = norm_axis(attr::int(node, "axis", 0), xs.len()) else { return vec![ValueType { dtype: x.dtype, shape: None }; n] };
    let total = xs[axis];
    let sizes: Vec<i64> = split_input.or_else(|| attr::ints(node, "split")).unwrap_or_else(|| {
        if total < 0 {
            return vec![-1; n];
        }
        let chunk = total / n as i64 + i64::from(total % n as i64 != 0); // opset 18 num_outputs: last chunk smaller
        (0..n as i64).map(|i| chunk.min(total - i * chunk).max(0)).collect()
    });
    sizes.iter().map(|&s| {
        let mut sh = xs.clone();
        sh[axis] = s;
        ValueType { dtype: x.dtype, shape: Some(sh) }
    }).collect()
}

fn slice(node: &NodeProto, x: &ValueType, starts: Option<Vec<i64>>, ends: Option<Vec<i64>>, axes: Option<Vec<i64>>, steps: Option<Vec<i64>>) -> ValueType {
    let legacy = node.input.len() == 1;
    let (starts, ends, axes) = if legacy {
        (attr::ints(node, "starts"), attr::ints(node, "ends"), attr::ints(node, "axes"))
    } else {
        let axes = if node.input.get(3).is_some_and(|s| !s.is_empty()) { axes } else { None };
        (starts, ends, axes)
    };
    let shape = (|| {
        let xs = x.shape.as_ref()?;
        let (starts, ends) = (starts?, ends?);
        let axes = axes.unwrap_or_else(|| (0..starts.len() as i64).collect());
        let steps = if !legacy && node.input.get(4).is_some_and(|s| !s.is_empty()) { steps? } else { vec![1; starts.len()] };
        let mut out = xs.clone();
        for i in 0..starts.len() {
            let a = norm_axis(*axes.get(i)?, xs.len())?;
            let dim = xs[a];
            if dim < 0 {
                out[a] = -1;
                continue;
            }
            let step = *steps.get(i)?;
            if step == 0 {
                return None;
            }
            let clampi = |v: i64, lo: i64, hi: i64| v.clamp(lo, hi);
            let fix = |v: i64| if v < 0 { v + dim } else { v };
            let (s, e) = if step > 0 {
                (clampi(fix(starts[i]), 0, dim), clampi(fix(*ends.get(i)?), 0, dim))
            } else {
                (clampi(fix(starts[i]), -1, dim - 1), clampi(fix(*ends.get(i)?), -1, dim - 1))
            };
            // s and e are clamped into [-1, dim]; a step of any size only needs its sign and magnitude.
            let stride = step.checked_abs().unwrap_or(i64::MAX);
            let span = if step > 0 { e - s } else { s - e };
            out[a] = if span <= 0 { 0 } else { (span - 1) / stride + 1 };
        }
        Some(out)
    })();
    ValueType { dtype: x.dtype, shape }
}

fn reshape(x: &ValueType, target: &[i64], allowzero: bool) -> Option<Vec<i64>> {
    let mut out: Vec<i64> = target.iter().enumerate().map(|(i, &d)| {
        if d == 0 && !allowzero { x.shape.as_ref().and_then(|s| s.get(i).copied()).unwrap_or(-1) } else { d }
    }).collect();
    if let Some(pos) = target.iter().position(|&d| d == -1) {
        let total: Option<i64> = x.shape.as_ref().and_then(|s| product(s));
        let known: i64 = out.iter().enumerate().filter(|&(i, _)| i != pos).try_fold(1i64, |a, (_, &d)| a.checked_mul(d)).unwrap_or(-1);
        out[pos] = match total {
            Some(t) if known > 0 && out.iter().enumerate().all(|(i, &d)| i == pos || d >= 0) => t / known,
            _ => -1,
        };
    }
    Some(out)
}

fn transpose(node: &NodeProto, x: &ValueType) -> ValueType {
    let shape = x.shape.as_ref().map(|xs| {
        let perm = attr::ints(node, "perm").unwrap_or_else(|| (0..xs.len() as i64).rev().collect());
        perm.iter().map(|&p| xs.get(p as usize).copied().unwrap_or(-1)).collect()
    });
    ValueType { dtype: x.dtype, shape }
}

fn resize(node: &NodeProto, x: &ValueType, cx: &Inferred) -> ValueType {
    let get = |i: usize| node.input.get(i).filter(|s| !s.is_empty()).and_then(|s| cx.consts.get(s));
    let shape = (|| {
        let xs = x.shape.as_ref()?;
        let (scales_i, sizes_i) = if node.op_type == "Upsample" || node.input.len() == 2 { (1, usize::MAX) } else { (2, 3) };
        let axes: Vec<usize> = match attr::ints(node, "axes") {
            Some(a) => a.iter().map(|&v| norm_axis(v, xs.len())).collect::<Option<_>>()?,
            None => (0..xs.len()).collect(),
        };
        if let Some(sizes) = get(sizes_i).and_then(|t| t.as_i64s()).filter(|s| !s.is_empty()) {
            let mut out = xs.clone();
            for (k, &a) in axes.iter().enumerate() {
                out[a] = *sizes.get(k)?;
            }
            return Some(out);
        }
        let scales: Vec<f64> = match get(scales_i) {
            Some(t) if !t.is_empty() && t.dtype().is_float() => t.data.to_f64(),
            _ => attr::find(node, "scales").map(|a| a.floats.iter().map(|&f| f as f64).collect())?,
        };
        let mut out = xs.clone();
        for (k, &a) in axes.iter().enumerate() {
            out[a] = if xs[a] < 0 { -1 } else { (xs[a] as f64 * scales.get(k)?).floor() as i64 };
        }
        Some(out)
    })();
    ValueType { dtype: x.dtype, shape }
}

fn flatten(node: &NodeProto, x: &ValueType) -> ValueType {
    let shape = x.shape.as_ref().map(|xs| {
        let a = attr::int(node, "axis", 1);
        let a = if a < 0 { a + xs.len() as i64 } else { a } as usize;
        let prod = |s: &[i64]| product(s).unwrap_or(-1);
        vec![prod(&xs[..a.min(xs.len())]), prod(&xs[a.min(xs.len())..])]
    });
    ValueType { dtype: x.dtype, shape }
}

fn gemm(node: &NodeProto, a: &ValueType, b: &ValueType) -> ValueType {
    let shape = (|| {
        let (a, b) = (a.shape.as_ref()?, b.shape.as_ref()?);
        let m = if attr::int(node, "transA", 0) != 0 { a.get(1)? } else { a.first()? };
        let n = if attr::int(node, "transB", 0) != 0 { b.first()? } else { b.get(1)? };
        Some(vec![*m, *n])
    })();
    ValueType { dtype: a.dtype, shape }
}

fn matmul(a: &ValueType, b: &ValueType, op: &str) -> ValueType {
    let shape = (|| {
        let (mut a, mut b) = (a.shape.clone().filter(|s| !s.is_empty())?, b.shape.clone().filter(|s| !s.is_empty())?);
        let (va, vb) = (a.len() == 1, b.len() == 1);
        if va { a.insert(0, 1) }
        if vb { b.push(1) }
        let (ra, rb) = (a.len(), b.len());
        let mut out = broadcast(&a[..ra - 2], &b[..rb - 2])?;
        if !va { out.push(a[ra - 2]) }
        if !vb { out.push(b[rb - 1]) }
        Some(out)
    })();
    ValueType { dtype: if op == "MatMul" { a.dtype } else { Some(DType::I32) }, shape }
}

fn reduce(node: &NodeProto, x: &ValueType, axes_input: Option<Vec<i64>>) -> ValueType {
    let has_input = node.input.get(1).is_some_and(|s| !s.is_empty());
    if has_input && axes_input.is_none() {
        return ValueType { dtype: x.dtype, shape: None };
    }
    reduce_axes(node, x, axes_input.or_else(|| attr::ints(node, "axes")))
}

fn reduce_axes(node: &NodeProto, x: &ValueType, axes: Option<Vec<i64>>) -> ValueType {
    let keep = attr::int(node, "keepdims", 1) != 0;
    let shape = x.shape.as_ref().and_then(|xs| {
        let axes: Vec<usize> = match axes.filter(|a| !a.is_empty()) {
            Some(a) => a.iter().map(|&v| norm_axis(v, xs.len())).collect::<Option<_>>()?,
            None if attr::int(node, "noop_with_empty_axes", 0) != 0 => vec![],
            None => (0..xs.len()).collect(),
        };
        Some(xs.iter().enumerate().filter_map(|(i, &d)| if axes.contains(&i) { keep.then_some(1) } else { Some(d) }).collect())
    });
    ValueType { dtype: x.dtype, shape }
}

fn shape_op(node: &NodeProto, x: &ValueType, cx: &mut Inferred) -> ValueType {
    let Some(xs) = x.shape.as_ref() else { return ValueType { dtype: Some(DType::I64), shape: None } };
    let r = xs.len() as i64;
    let clampr = |v: i64| (if v < 0 { v + r } else { v }).clamp(0, r) as usize;
    let (s, e) = (clampr(attr::int(node, "start", 0)), clampr(attr::int(node, "end", r)));
    let dims = xs[s..e.max(s)].to_vec();
    if dims.iter().all(|&d| d >= 0) {
        cx.consts.insert(node.output[0].clone(), Tensor::new(vec![dims.len()], TensorData::I64(dims.clone())));
    }
    ValueType { dtype: Some(DType::I64), shape: Some(vec![dims.len() as i64]) }
}

fn gather(node: &NodeProto, x: &ValueType, idx: &ValueType, cx: &mut Inferred) -> ValueType {
    let shape = (|| {
        let xs = x.shape.as_ref()?;
        let is = idx.shape.as_ref()?;
        let a = norm_axis(attr::int(node, "axis", 0), xs.len())?;
        let mut out = xs[..a].to_vec();
        out.extend(is);
        out.extend(&xs[a + 1..]);
        Some(out)
    })();
    // Shape arithmetic: gather from a 1-D constant.
    let data = cx.consts.get(&node.input[0]).and_then(|t| t.as_i64s().map(|v| (t.shape.clone(), v)));
    let ids = node.input.get(1).and_then(|n| cx.consts.get(n)).map(|t| (t.shape.clone(), t.as_i64s()));
    if let (Some((ds, d)), Some((is, Some(i)))) = (data, ids) {
        if ds.len() == 1 && attr::int(node, "axis", 0) == 0 {
            let n = d.len() as i64;
            let vals: Option<Vec<i64>> = i.iter().map(|&k| d.get((if k < 0 { k + n } else { k }) as usize).copied()).collect();
            if let Some(v) = vals {
                cx.consts.insert(node.output[0].clone(), Tensor::new(is, TensorData::I64(v)));
            }
        }
    }
    ValueType { dtype: x.dtype, shape }
}

fn axes_of(node: &NodeProto, input: Option<Vec<i64>>) -> Option<Vec<i64>> {
    input.or_else(|| attr::ints(node, "axes"))
}

fn unsqueeze(node: &NodeProto, x: &ValueType, axes_in: Option<Vec<i64>>, cx: &mut Inferred) -> ValueType {
    let shape = (|| {
        let xs = x.shape.as_ref()?;
        let axes = axes_of(node, axes_in)?;
        let r = xs.len() + axes.len();
        let mut ax: Vec<usize> = axes.iter().map(|&a| norm_axis(a, r)).collect::<Option<_>>()?;
        ax.sort();
        let mut out = xs.clone();
        for a in ax {
            out.insert(a.min(out.len()), 1);
        }
        Some(out)
    })();
    reshape_const(node, &shape, cx);
    ValueType { dtype: x.dtype, shape }
}

fn squeeze(node: &NodeProto, x: &ValueType, axes_in: Option<Vec<i64>>, cx: &mut Inferred) -> ValueType {
    let shape = x.shape.as_ref().and_then(|xs| match axes_of(node, axes_in) {
        Some(a) => {
            let ax: Vec<usize> = a.iter().map(|&v| norm_axis(v, xs.len())).collect::<Option<_>>()?;
            Some(xs.iter().enumerate().filter(|(i, _)| !ax.contains(i)).map(|(_, &d)| d).collect())
        }
        None => Some(xs.iter().copied().filter(|&d| d != 1).collect()),
    });
    reshape_const(node, &shape, cx);
    ValueType { dtype: x.dtype, shape }
}

/// Unsqueeze/Squeeze of a constant is the same values with a new shape.
fn reshape_const(node: &NodeProto, shape: &Option<Vec<i64>>, cx: &mut Inferred) {
    if let (Some(t), Some(s)) = (cx.consts.get(&node.input[0]).cloned(), shape) {
        if s.iter().all(|&d| d >= 0) {
            cx.consts.insert(node.output[0].clone(), Tensor::new(s.iter().map(|&d| d as usize).collect(), t.data));
        }
    }
}

fn constant(node: &NodeProto, cx: &mut Inferred) -> ValueType {
    let t: Option<Tensor> = if let Some(tp) = attr::tensor(node, "value") {
        to_tensor(tp).ok()
    } else if let Some(a) = attr::find(node, "value_float") {
        Some(Tensor::new(vec![], TensorData::F32(vec![a.f.unwrap_or(0.0)])))
    } else if let Some(a) = attr::find(node, "value_floats") {
        Some(Tensor::new(vec![a.floats.len()], TensorData::F32(a.floats.clone())))
    } else if let Some(a) = attr::find(node, "value_int") {
        Some(Tensor::new(vec![], TensorData::I64(vec![a.i.unwrap_or(0)])))
    } else if let Some(a) = attr::find(node, "value_ints") {
        Some(Tensor::new(vec![a.ints.len()], TensorData::I64(a.ints.clone())))
    } else {
        None
    };
    match t {
        Some(t) => {
            let vt = ValueType { dtype: Some(t.dtype()), shape: Some(t.shape.iter().map(|&d| d as i64).collect()) };
            if t.len() <= MAX_CONST_ELEMS {
                cx.consts.insert(node.output[0].clone(), t);
            }
            vt
        }
        None => ValueType::default(),
    }
}

fn constant_of_shape(node: &NodeProto, shape: Option<Vec<i64>>, cx: &mut Inferred) -> ValueType {
    let value = attr::tensor(node, "value").and_then(|t| to_tensor(t).ok());
    let dtype = value.as_ref().map_or(DType::F32, |v| v.dtype());
    if let (Some(s), Some(v)) = (&shape, &value) {
        let n: i64 = s.iter().try_fold(1i64, |a, &d| a.checked_mul(d)).unwrap_or(-1);
        if (0..=MAX_CONST_ELEMS as i64).contains(&n) {
            if let Some(fill) = v.as_i64s().and_then(|f| f.first().copied()) {
                let data = TensorData::I64(vec![fill; n as usize]);
                let t = Tensor::new(s.iter().map(|&d| d as usize).collect(), data);
                cx.consts.insert(node.output[0].clone(), cast_like(t, dtype));
            }
        }
    }
    ValueType { dtype: Some(dtype), shape }
}

fn pad(node: &NodeProto, x: &ValueType, pads_in: Option<Vec<i64>>) -> ValueType {
    let shape = (|| {
        let xs = x.shape.as_ref()?;
        let pads = pads_in.or_else(|| attr::ints(node, "pads"))?;
        let n = xs.len();
        if node.input.get(3).is_some_and(|s| !s.is_empty()) {
            return None; // axes input: rare; leave unknown rather than guess
        }
        (0..n).map(|i| Some(if xs[i] < 0 { -1 } else { xs[i].checked_add(*pads.get(i)?)?.checked_add(*pads.get(i + n)?)? })).collect::<Option<Vec<i64>>>()
    })();
    ValueType { dtype: x.dtype, shape }
}

fn range(node: &NodeProto, cx: &mut Inferred) -> ValueType {
    let get = |i: usize| cx.consts.get(&node.input[i]).map(|t| (t.dtype(), t.data.to_f64()));
    let dtype = node.input.first().and_then(|n| cx.types.get(n)).and_then(|t| t.dtype);
    let (Some(s), Some(l), Some(d)) = (get(0), get(1), get(2)) else { return ValueType { dtype, shape: Some(vec![-1]) } };
    let (start, limit, delta) = (s.1[0], l.1[0], d.1[0]);
    if delta == 0.0 {
        return ValueType { dtype, shape: None };
    }
    let n = ((limit - start) / delta).ceil().max(0.0) as i64;
    if n as usize <= MAX_CONST_ELEMS && !s.0.is_float() {
        let v: Vec<i64> = (0..n).map(|i| (start + i as f64 * delta) as i64).collect();
        cx.consts.insert(node.output[0].clone(), cast_like(Tensor::new(vec![n as usize], TensorData::I64(v)), s.0));
    }
    ValueType { dtype, shape: Some(vec![n]) }
}

fn depth_space(node: &NodeProto, x: &ValueType) -> ValueType {
    let b = attr::int(node, "blocksize", 1);
    let shape = x.shape.as_ref().filter(|s| b > 0 && s.len() == 4 && s.iter().all(|&d| d >= 0)).map(|s| {
        let m = |a: i64, b: i64| a.checked_mul(b).unwrap_or(-1);
        let bb = b.checked_mul(b).unwrap_or(i64::MAX);
        if node.op_type == "DepthToSpace" { vec![s[0], s[1] / bb, m(s[2], b), m(s[3], b)] } else { vec![s[0], m(s[1], bb), s[2] / b, s[3] / b] }
    });
    ValueType { dtype: x.dtype, shape }
}

fn cast_like(t: Tensor, dtype: DType) -> Tensor {
    let v = t.as_i64s().unwrap_or_default();
    let data = match dtype {
        DType::I32 => TensorData::I32(v.iter().map(|&x| x as i32).collect()),
        DType::F32 => TensorData::F32(v.iter().map(|&x| x as f32).collect()),
        DType::F64 => TensorData::F64(v.iter().map(|&x| x as f64).collect()),
        DType::Bool => TensorData::Bool(v.iter().map(|&x| x != 0).collect()),
        _ => TensorData::I64(v),
    };
    Tensor::new(t.shape, data)
}

/// Integer arithmetic on carried constants: the rest of PyTorch's shape chains.
fn fold_int_consts(node: &NodeProto, cx: &mut Inferred) {
    let get = |i: usize| node.input.get(i).and_then(|n| cx.consts.get(n)).cloned();
    let out = match node.op_type.as_str() {
        "Identity" => get(0),
        "Reshape" => (|| {
            let (t, target) = (get(0)?, get(1)?.as_i64s()?);
            let from = ValueType { dtype: Some(t.dtype()), shape: Some(t.shape.iter().map(|&d| d as i64).collect()) };
            let shape: Vec<usize> = reshape(&from, &target, false)?.iter().map(|&d| usize::try_from(d).ok()).collect::<Option<_>>()?;
            (shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)) == Some(t.len())).then(|| Tensor::new(shape, t.data))
        })(),
        "Cast" => get(0).filter(|t| t.as_i64s().is_some()).and_then(|t| {
            let to = DType::from_onnx(attr::int(node, "to", 0) as i32)?;
            (!matches!(to, DType::F16 | DType::Bf16 | DType::Str)).then(|| cast_like(t, to))
        }),
        "Concat" => (0..node.input.len()).map(get).collect::<Option<Vec<Tensor>>>().and_then(|ts| concat_consts(&ts)),
        "Add" | "Sub" | "Mul" | "Div" | "Equal" | "Where" if node.op_type != "Where" || node.input.len() == 3 => {
            let ts: Option<Vec<Tensor>> = (0..node.input.len()).map(get).collect();
            ts.and_then(|ts| int_elementwise(&node.op_type, &ts))
        }
        "Slice" if node.input.len() >= 3 => (|| {
            let data = get(0)?;
            if data.shape.len() != 1 {
                return None;
            }
            let v = data.as_i64s()?;
            let n = v.len() as i64;
            let (s, e) = (get(1)?.as_i64s()?[0], get(2)?.as_i64s()?[0]);
            let step = get(4).and_then(|t| t.as_i64s()).map_or(1, |t| t[0]);
            if step != 1 {
                return None;
            }
            let fix = |x: i64| (if x < 0 { x + n } else { x }).clamp(0, n) as usize;
            let r = v[fix(s)..fix(e).max(fix(s))].to_vec();
            Some(cast_like(Tensor::new(vec![r.len()], TensorData::I64(r)), data.dtype()))
        })(),
        _ => None,
    };
    if let Some(t) = out {
        cx.consts.insert(node.output[0].clone(), t);
    }
}

/// Concatenates 1-D constants: int shape pieces, or float Resize scales ([1, 1] ++ factors).
fn concat_consts(ts: &[Tensor]) -> Option<Tensor> {
    if ts.iter().any(|t| t.shape.len() != 1) {
        return None;
    }
    let dt = ts.first()?.dtype();
    if dt == DType::F32 {
        let v: Vec<f32> = ts.iter().map(|t| t.as_f32().map(<[f32]>::to_vec)).collect::<Option<Vec<_>>>()?.concat();
        return Some(Tensor::new(vec![v.len()], TensorData::F32(v)));
    }
    let v: Vec<i64> = ts.iter().map(|t| t.as_i64s()).collect::<Option<Vec<_>>>()?.concat();
    Some(cast_like(Tensor::new(vec![v.len()], TensorData::I64(v)), dt))
}

fn int_elementwise(op: &str, ts: &[Tensor]) -> Option<Tensor> {
    let vals: Vec<Vec<i64>> = ts.iter().map(|t| t.as_i64s()).collect::<Option<_>>()?;
    if ts.iter().any(|t| t.dtype().is_float()) {
        return None;
    }
    let n = vals.iter().map(|v| v.len()).max()?;
    if vals.iter().any(|v| v.len() != n && v.len() != 1) {
        return None;
    }
    let at = |v: &Vec<i64>, i: usize| if v.len() == 1 { v[0] } else { v[i] };
    let shape = ts.iter().find(|t| t.len() == n).map(|t| t.shape.clone())?;
    let r: Vec<i64> = (0..n).map(|i| {
        let (a, b) = (at(&vals[0], i), vals.get(1).map_or(0, |v| at(v, i)));
        Some(match op {
            "Add" => a.wrapping_add(b),
            "Sub" => a.wrapping_sub(b),
            "Mul" => a.wrapping_mul(b),
            "Div" => a.checked_div(b)?, // ONNX integer Div truncates, like Rust; /0 and MIN/-1 stay unknown
            "Equal" => (a == b) as i64,
            "Where" => if a != 0 { b } else { at(&vals[2], i) },
            _ => return None,
        })
    }).collect::<Option<_>>()?;
    let dt = match op { "Equal" => DType::Bool, "Where" => ts[1].dtype(), _ => ts[0].dtype() };
    Some(cast_like(Tensor::new(shape, TensorData::I64(r)), dt))
}

/// The model's one image input (initializer-shadowing inputs aside), which must be a fixed
/// [1, C, H, W]; `who` names what needs it in the error.
pub fn static_image_input(g: &crate::onnx::proto::GraphProto, who: &str) -> anyhow::Result<(String, [usize; 4])> {
    use anyhow::{anyhow, bail};
    let inits: std::collections::HashSet<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
    let inputs: Vec<_> = g.input.iter().filter(|v| !inits.contains(v.name.as_str())).collect();
    let [input] = inputs[..] else { bail!("{who} needs one image input; this model has {} (bind the blur map with bind-psf and --psf)", inputs.len()) };
    let shape = declared(input).static_shape().ok_or_else(|| anyhow!("{who} needs a fixed input shape; '{}' has none (export with static shapes)", input.name))?;
    let [1, c, h, w] = shape[..] else { bail!("{who} needs a [1, C, H, W] image input; '{}' is {shape:?}", input.name) };
    Ok((input.name.clone(), [1, c, h, w]))
}
