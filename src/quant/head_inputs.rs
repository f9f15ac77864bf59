//! The detector's last convolutions read float activations.
//!
//! A YOLOv8 box output is a softmax over 16 distance bins per side, and the box edge is its
//! expectation: rounding the activation its convolution reads shifts every logit a little,
//! which moves the edge by a fraction of a bin, and at stride 8 a bin is 8 pixels of a box a
//! few bins wide, which IoU at 0.75-0.95 sees. Measured on the trained width-0.25 v8 (200
//! held-out frames, `detect-int8`, calibration seed 0): INT8 agreed with float's detections
//! at 0.966 (mAP@0.5:0.95) and lost 0.0167 of mAP against labels; with the stride-8 box
//! convolution and the SiLU before it float, 0.990 and 0.008; any other region of the network
//! float (encoder, bridge, backbone, neck) left it within 0.003 of where it was (record
//! `int8-regions`). The last convolutions are 1x1 over the head's maps: about 1% of the
//! detector's MACs.
//!
//! The value a last convolution reads is float when its producer and the convolution are:
//! the producer's other readers, if any, quantize it at their own inputs.

use crate::analysis::channels::detector_convolutions;
use crate::ir::Graph;
use std::collections::BTreeMap;

/// Nodes that stay float so that the detector's last convolutions read float values: node
/// name -> why.
pub fn head_inputs(g: &Graph) -> BTreeMap<String, String> {
    let mut out = BTreeMap::new();
    for i in detector_convolutions(g) {
        let n = g.node(i);
        out.insert(n.name.clone(), "a last convolution of the detector: reads a float value".to_string());
        if let Some(p) = n.input.first().and_then(|x| g.producer_of(x)) {
            out.entry(p.name.clone()).or_insert_with(|| format!("writes the value the last convolution '{}' reads", n.name));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::onnx::edit::tensor_value_info;
    use crate::onnx::proto::{GraphProto, NodeProto, TensorProto};
    use crate::tensor::DType;

    #[test]
    fn the_last_convolutions_and_the_producers_of_what_they_read_stay_float() {
        let node = |name: &str, op: &str, i: &[&str], o: &str| NodeProto { name: name.into(), op_type: op.into(), input: i.iter().map(|s| s.to_string()).collect(), output: vec![o.into()], ..Default::default() };
        let w = |name: &str, dims: [i64; 4]| TensorProto { name: name.into(), dims: dims.to_vec(), data_type: 1, float_data: vec![0.0; dims.iter().product::<i64>() as usize], ..Default::default() };
        let g = GraphProto {
            node: vec![
                node("trunk", "Conv", &["x", "w0", ""], "a"),
                node("sig", "Sigmoid", &["a"], "s"),
                node("silu", "Mul", &["a", "s"], "b"),
                node("down", "Conv", &["b", "w1", ""], "c"), // another reader of b
                node("box", "Conv", &["b", "w2", ""], "y1"),
                node("cls", "Conv", &["c", "w3", ""], "y2"),
            ],
            initializer: vec![w("w0", [16, 1, 3, 3]), w("w1", [16, 16, 3, 3]), w("w2", [64, 16, 1, 1]), w("w3", [6, 16, 1, 1])],
            input: vec![tensor_value_info("x", DType::F32, &[1, 1, 16, 16])],
            output: vec![tensor_value_info("y1", DType::F32, &[1, 64, 16, 16]), tensor_value_info("y2", DType::F32, &[1, 6, 16, 16])],
            ..Default::default()
        };
        let graph = Graph::build(&g).unwrap();
        let f = head_inputs(&graph);
        assert_eq!(f.keys().map(|s| s.as_str()).collect::<Vec<_>>(), ["box", "cls", "down", "silu"]);
        assert!(f["silu"].contains("'box'") && f["down"].contains("'cls'"), "{f:?}");
        assert!(f["box"].starts_with("a last convolution"));
    }
}
