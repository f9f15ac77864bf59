//! Which detector head a graph ends in: YOLOv5 anchor decode, YOLOv8 DFL decode, or raw.

use crate::ir::{Graph, Inferred};
use crate::onnx::tensor_proto::to_tensor;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum HeadKind {
    /// sigmoid -> (xy*2-0.5+grid)*stride, (wh*2)^2*anchor -> [1, N, 5+nc]
    Yolov5Anchor,
    /// softmax over reg_max bins -> fixed arange conv -> dist2bbox -> [1, 4+nc, N]
    Yolov8Dfl,
    /// convolution outputs without in-graph decode
    Raw,
}

#[derive(Clone, Debug, Serialize)]
pub struct Head {
    pub kind: HeadKind,
    /// The decoded detection output (the first detection output for raw heads).
    pub output: Option<String>,
    pub classes: Option<usize>,
    /// DFL bins (YOLOv8 only).
    pub reg_max: Option<usize>,
}

pub fn detect(g: &Graph, inf: &Inferred, det_outputs: &[String]) -> Head {
    let cone = g.cone(det_outputs.iter().map(|s| s.as_str()));
    let in_cone = |op: &str| g.order.iter().filter(|&&i| cone[i] && g.node(i).op_type == op).map(|&i| g.node(i)).collect::<Vec<_>>();
    let out = det_outputs.iter().find(|o| inf.shape(o).is_some_and(|s| s.len() == 3)).cloned();
    let out_shape = out.as_ref().and_then(|o| inf.shape(o));

    // DFL: a Softmax feeding a 1-output Conv whose weights are 0, 1, ..., R-1.
    for sm in in_cone("Softmax") {
        for &c in g.consumers_of(&sm.output[0]) {
            let conv = g.node(c);
            if conv.op_type != "Conv" {
                continue;
            }
            let w = conv.input.get(1).and_then(|n| g.initializers.get(n.as_str())).and_then(|t| to_tensor(t).ok());
            if let Some(v) = w.as_ref().and_then(|w| w.as_f32()) {
                if v.len() > 1 && v.iter().enumerate().all(|(i, &x)| x == i as f32) {
                    let classes = out_shape.as_ref().and_then(|s| s[1].checked_sub(4));
                    return Head { kind: HeadKind::Yolov8Dfl, output: out, classes, reg_max: Some(v.len()) };
                }
            }
        }
    }
    // YOLOv5: a sigmoid'ed head whose wh branch is squared (Pow 2) and scaled by anchors.
    let squares = in_cone("Pow").into_iter().any(|p| {
        p.input.get(1).and_then(|n| inf.consts.get(n)).is_some_and(|t| t.data.to_f64().first() == Some(&2.0))
    });
    if squares && !in_cone("Sigmoid").is_empty() {
        let classes = out_shape.as_ref().and_then(|s| s[2].checked_sub(5));
        return Head { kind: HeadKind::Yolov5Anchor, output: out, classes, reg_max: None };
    }
    Head { kind: HeadKind::Raw, output: det_outputs.first().cloned(), classes: None, reg_max: None }
}
