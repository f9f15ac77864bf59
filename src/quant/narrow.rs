//! Narrow layers stay float: where ONNX Runtime's integer convolution loses to its float one
//! by the layer's shape, not by measurement, so that the same recipe gives the same bytes on
//! every machine.
//!
//! ORT's QLinearConv runs a convolution as a product over output channels packed 16 wide
//! (and a depthwise one through its own loop); its float convolution runs NCHWc blocks with a
//! direct kernel. A convolution with fewer than 16 output channels per group (the stem at full
//! resolution, depthwise and grouped convolutions, anything pruned to 8 channels) fills a
//! fraction of the integer kernel and moves its whole map through it. Measured on the width-0.25
//! v5 at 640x480 on 2 cores (ORT 1.31.1, per-kernel profile medians): the stem (1 -> 8
//! channels) 3.42 ms as QLinearConv, 0.55 ms float; the 15x15 depthwise convolution of the
//! PALS-Bridge 3.17 against 1.68 ms; the bridge's grouped convolution (8 per group) 1.90
//! against 1.06 ms; pruned to 2 channels, the stem's second convolution 3.59 against 0.85 ms.
//! At 16 channels and more the integer kernel wins (2-3x at 16-32 channels).
//!
//! A float convolution between integer ones costs a dequantize and a quantize of its map, so
//! the element-wise and data-movement nodes that read only float narrow layers stay float
//! with them. The nodes that read the float region directly stay float as well, and the
//! region ends after them: ONNX Runtime quantizes the float weights of a convolution that
//! sits between a DequantizeLinear and a QuantizeLinear itself (and drops a Relu before a
//! QuantizeLinear), so a QuantizeLinear right after the region would bring the narrow
//! convolution back as a QLinearConv. Measured before this rule, with `narrow_float: 16` on the
//! width-0.25 v5 at 640x480: the PALS-Bridge's 15x15 depthwise convolution, read by a 1x1
//! convolution, ran as QLinearConv in 4.98 ms (float: 1.70 ms).

use crate::ir::Graph;
use crate::onnx::attr;
use std::collections::{BTreeMap, BTreeSet};

/// Nodes that stay float with the narrow convolutions: node name -> why.
pub fn narrow_float(g: &Graph, min_channels: usize) -> BTreeMap<String, String> {
    let mut out: BTreeMap<String, String> = BTreeMap::new();
    if min_channels == 0 {
        return out;
    }
    for &i in &g.order {
        let n = g.node(i);
        let Some(weights) = (n.op_type == "Conv").then(|| n.input.get(1).and_then(|w| g.initializers.get(w.as_str()))).flatten() else { continue };
        let groups = attr::int(n, "group", 1).max(1) as usize;
        let per_group = weights.dims.first().map_or(0, |&c| c.max(0) as usize) / groups;
        if per_group < min_channels {
            out.insert(n.name.clone(), format!("{per_group} output channel(s) per group: ONNX Runtime's integer convolution is slower than its float one below {min_channels}"));
        }
    }
    // Readers of float narrow layers only, in graph order (a node's producers come first).
    for &i in &g.order {
        let n = g.node(i);
        if out.contains_key(&n.name) || !FOLLOWERS.contains(&n.op_type.as_str()) {
            continue;
        }
        let mut produced = n.input.iter().filter(|v| !v.is_empty() && !g.initializers.contains_key(v.as_str())).map(|v| g.producer_of(v)).peekable();
        if produced.peek().is_some() && produced.all(|p| p.is_some_and(|p| out.contains_key(&p.name))) {
            out.insert(n.name.clone(), "reads only float narrow layers".into());
        }
    }
    // The region's direct readers, one step (a float node's readers may be quantized again:
    // their QuantizeLinear then follows a node ONNX Runtime does not fuse into an integer one).
    let region: BTreeSet<String> = out.keys().cloned().collect();
    for &i in &g.order {
        let n = g.node(i);
        if out.contains_key(&n.name) {
            continue;
        }
        if n.input.iter().filter(|v| !v.is_empty()).any(|v| g.producer_of(v).is_some_and(|p| region.contains(&p.name))) {
            out.insert(n.name.clone(), "reads a float narrow layer directly: a QuantizeLinear there would let ONNX Runtime turn that layer back into an integer one".into());
        }
    }
    out
}

/// Nodes that follow a float region rather than start a quantized one.
const FOLLOWERS: &[&str] = &["Relu", "Sigmoid", "Mul", "Add", "MaxPool", "Concat", "Clip", "LeakyRelu"];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::onnx::edit::tensor_value_info;
    use crate::onnx::proto::{GraphProto, NodeProto, TensorProto};
    use crate::tensor::DType;

    fn conv(name: &str, x: &str, w: &str, y: &str, group: i64) -> NodeProto {
        let mut n = NodeProto { name: name.into(), op_type: "Conv".into(), input: vec![x.into(), w.into()], output: vec![y.into()], ..Default::default() };
        if group > 1 {
            n.attribute.push(attr::make_int("group", group));
        }
        n
    }

    fn weights(name: &str, dims: [i64; 4]) -> TensorProto {
        TensorProto { name: name.into(), dims: dims.to_vec(), data_type: 1, float_data: vec![0.0; dims.iter().product::<i64>() as usize], ..Default::default() }
    }

    #[test]
    fn narrow_convolutions_what_reads_only_them_and_their_direct_readers_stay_float() {
        let node = |name: &str, op: &str, i: &[&str], o: &str| NodeProto { name: name.into(), op_type: op.into(), input: i.iter().map(|s| s.to_string()).collect(), output: vec![o.into()], ..Default::default() };
        let g = GraphProto {
            node: vec![
                conv("stem", "x", "w0", "a", 1),          // 8 out: narrow
                node("relu", "Relu", &["a"], "b"),        // reads the stem only
                conv("wide", "b", "w1", "c", 1),          // 16 out
                conv("dw", "c", "w2", "d", 16),           // depthwise: 1 per group
                node("sum", "Add", &["c", "d"], "e"),     // reads a wide layer too
                node("pool", "MaxPool", &["d"], "f"),
            ],
            initializer: vec![weights("w0", [8, 1, 3, 3]), weights("w1", [16, 8, 3, 3]), weights("w2", [16, 1, 15, 15])],
            input: vec![tensor_value_info("x", DType::F32, &[1, 1, 32, 32])],
            output: vec![tensor_value_info("e", DType::F32, &[1, 16, 32, 32]), tensor_value_info("f", DType::F32, &[1, 16, 16, 16])],
            ..Default::default()
        };
        let graph = Graph::build(&g).unwrap();
        let f = narrow_float(&graph, 16);
        assert_eq!(f.keys().map(|s| s.as_str()).collect::<Vec<_>>(), ["dw", "pool", "relu", "stem", "sum", "wide"]);
        assert!(f["stem"].starts_with("8 output channel(s) per group"), "{}", f["stem"]);
        assert!(f["dw"].starts_with("1 output channel(s) per group"));
        assert!(f["wide"].starts_with("reads a float narrow layer directly") && f["sum"].starts_with("reads a float narrow layer directly"));
        assert!(narrow_float(&graph, 8).keys().eq(["dw", "pool", "sum"].iter()), "8 channels are not below 8");
        assert!(narrow_float(&graph, 0).is_empty(), "0: off");
    }
}
