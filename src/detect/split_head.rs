//! Post-processing for split heads: what runs on the CPU after an NPU that stops at the
//! detector's last convolutions (see the `rknn-legalize` pass).
//!
//! Per stride the model gives `boxes_s{S}` and `scores_s{S}` (and, for YOLOv8,
//! `score_sum_s{S}`), NCHW. [`decode_dense`] rebuilds exactly the tensor the original
//! in-graph decode produced ([1, N, 5+nc] for YOLOv5, [1, 4+nc, N] for YOLOv8), so the two can
//! be compared number for number; [`detect`] is the deployment path: it skips cells that
//! cannot hold a detection above `conf` before decoding anything, then runs class-aware NMS.
//! Skipping is exact: YOLOv5's score is obj × cls ≤ obj, and YOLOv8's best class score is ≤
//! the clipped sum of its scores (conf < 1), so a skipped cell never held a candidate.

use super::{nms::nms, Detection};
use crate::analysis::head::HeadKind;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// Everything post-processing needs to know about a split head; stored in the model's
/// metadata (`pdi.head_layout`) and in the target's configuration.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct HeadLayout {
    pub kind: HeadKind,
    pub classes: usize,
    /// DFL bins (YOLOv8).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reg_max: Option<usize>,
    /// Finest stride first, the order of the original decode's rows.
    pub levels: Vec<Level>,
    /// Where the input's top-left pixel lies in the frame (x, y): a model cropped to a scene's
    /// ROI decodes boxes in frame coordinates.
    #[serde(default, skip_serializing_if = "is_origin")]
    pub offset: [f32; 2],
}

fn is_origin(o: &[f32; 2]) -> bool {
    *o == [0.0, 0.0]
}

#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct Level {
    pub stride: usize,
    pub height: usize,
    pub width: usize,
    /// YOLOv5 anchor sizes in input pixels, one (w, h) per anchor.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub anchors: Vec<[f32; 2]>,
    pub boxes: String,
    pub scores: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score_sum: Option<String>,
}

/// Metadata key the layout is stored under.
pub const METADATA_KEY: &str = "pdi.head_layout";

impl HeadLayout {
    pub fn output_names(&self) -> Vec<String> {
        self.levels.iter().flat_map(|l| [Some(l.boxes.clone()), Some(l.scores.clone()), l.score_sum.clone()]).flatten().collect()
    }

    /// Candidate rows over all levels (anchors × cells).
    pub fn rows(&self) -> usize {
        self.levels.iter().map(|l| l.height * l.width * l.anchors.len().max(1)).sum()
    }

    /// Reads the layout a legalized model carries.
    pub fn from_model(model: &crate::onnx::proto::ModelProto) -> Result<HeadLayout> {
        let p = model.metadata_props.iter().find(|p| p.key == METADATA_KEY).ok_or_else(|| {
            anyhow!("the model carries no '{METADATA_KEY}' metadata: compile it with a recipe that ends in the rknn-legalize pass")
        })?;
        serde_json::from_str(&p.value).map_err(|e| anyhow!("metadata '{METADATA_KEY}' is not a head layout: {e}"))
    }
}

/// One level's tensors, checked against the layout.
struct LevelData<'a> {
    boxes: &'a [f32],
    scores: &'a [f32],
    score_sum: Option<&'a [f32]>,
}

fn level_data<'a>(layout: &HeadLayout, l: &Level, out: &'a HashMap<String, Tensor>) -> Result<LevelData<'a>> {
    let (box_ch, score_ch) = match layout.kind {
        HeadKind::Yolov5Anchor => (l.anchors.len() * 4, l.anchors.len() * (1 + layout.classes)),
        HeadKind::Yolov8Dfl => (4 * layout.reg_max.unwrap_or(16), layout.classes),
        HeadKind::Raw => bail!("a raw head has no layout to decode"),
    };
    let get = |name: &str, channels: usize| -> Result<&'a [f32]> {
        let t = out.get(name).ok_or_else(|| anyhow!("output '{name}' is missing"))?;
        let v = t.as_f32().ok_or_else(|| anyhow!("output '{name}' is not float32"))?;
        if t.shape != [1, channels, l.height, l.width] {
            bail!("output '{name}' has shape {:?}; the head layout says [1, {channels}, {}, {}]", t.shape, l.height, l.width);
        }
        Ok(v)
    };
    Ok(LevelData {
        boxes: get(&l.boxes, box_ch)?,
        scores: get(&l.scores, score_ch)?,
        score_sum: l.score_sum.as_deref().map(|n| get(n, 1)).transpose()?,
    })
}

/// YOLOv5 box of anchor `a` at cell (x, y): sigmoid outputs → (cx, cy, w, h) in pixels.
fn v5_box(l: &Level, offset: [f32; 2], d: &LevelData, a: usize, x: usize, y: usize) -> [f32; 4] {
    let cells = l.height * l.width;
    let at = |j: usize| d.boxes[(a * 4 + j) * cells + y * l.width + x];
    let s = l.stride as f32;
    let [aw, ah] = l.anchors[a];
    let [ox, oy] = offset;
    [(at(0) * 2.0 - 0.5 + x as f32) * s + ox, (at(1) * 2.0 - 0.5 + y as f32) * s + oy, (at(2) * 2.0).powi(2) * aw, (at(3) * 2.0).powi(2) * ah]
}

/// YOLOv8 box at cell (x, y): softmax-expected distance per side → (cx, cy, w, h) in pixels.
fn v8_box(l: &Level, offset: [f32; 2], d: &LevelData, reg_max: usize, x: usize, y: usize) -> [f32; 4] {
    let cells = l.height * l.width;
    let cell = y * l.width + x;
    let mut dist = [0f32; 4];
    for (side, out) in dist.iter_mut().enumerate() {
        let logit = |r: usize| d.boxes[(side * reg_max + r) * cells + cell];
        let m = (0..reg_max).map(logit).fold(f32::MIN, f32::max);
        let (mut num, mut den) = (0f32, 0f32);
        for r in 0..reg_max {
            let e = (logit(r) - m).exp();
            num += e * r as f32;
            den += e;
        }
        *out = num / den;
    }
    let (ax, ay) = (x as f32 + 0.5, y as f32 + 0.5);
    let (x1, y1, x2, y2) = (ax - dist[0], ay - dist[1], ax + dist[2], ay + dist[3]);
    let s = l.stride as f32;
    let [ox, oy] = offset;
    [(x1 + x2) / 2.0 * s + ox, (y1 + y2) / 2.0 * s + oy, (x2 - x1) * s, (y2 - y1) * s]
}

/// The original model's decoded output, rebuilt from the split tensors.
pub fn decode_dense(layout: &HeadLayout, out: &HashMap<String, Tensor>) -> Result<Tensor> {
    let nc = layout.classes;
    let n = layout.rows();
    match layout.kind {
        HeadKind::Yolov5Anchor => {
            let no = 5 + nc;
            let mut rows = Vec::with_capacity(n * no);
            for l in &layout.levels {
                let d = level_data(layout, l, out)?;
                let cells = l.height * l.width;
                for a in 0..l.anchors.len() {
                    for y in 0..l.height {
                        for x in 0..l.width {
                            rows.extend(v5_box(l, layout.offset, &d, a, x, y));
                            rows.extend((0..1 + nc).map(|k| d.scores[(a * (1 + nc) + k) * cells + y * l.width + x]));
                        }
                    }
                }
            }
            Ok(Tensor::f32(vec![1, n, no], rows))
        }
        HeadKind::Yolov8Dfl => {
            let reg_max = layout.reg_max.unwrap_or(16);
            let mut cols = vec![0f32; (4 + nc) * n];
            let mut i = 0;
            for l in &layout.levels {
                let d = level_data(layout, l, out)?;
                let cells = l.height * l.width;
                for y in 0..l.height {
                    for x in 0..l.width {
                        let b = v8_box(l, layout.offset, &d, reg_max, x, y);
                        for (c, v) in b.into_iter().chain((0..nc).map(|k| d.scores[k * cells + y * l.width + x])).enumerate() {
                            cols[c * n + i] = v;
                        }
                        i += 1;
                    }
                }
            }
            Ok(Tensor::f32(vec![1, 4 + nc, n], cols))
        }
        HeadKind::Raw => bail!("a raw head has no layout to decode"),
    }
}

/// How much of the head the deployment path looked at.
#[derive(Clone, Copy, Debug, Default, Serialize, PartialEq)]
pub struct Skipped {
    pub cells: usize,
    /// Cells (× anchors for YOLOv5) whose boxes were never decoded.
    pub skipped: usize,
}

/// Detections above `conf` after class-aware NMS, decoding only cells that can hold one.
pub fn detect(layout: &HeadLayout, out: &HashMap<String, Tensor>, conf: f32, iou: f32, max_det: usize) -> Result<(Vec<Detection>, Skipped)> {
    let nc = layout.classes;
    let mut found = Vec::new();
    let mut stats = Skipped::default();
    let mut push = |b: [f32; 4], class: usize, score: f32| {
        if score > conf && score.is_finite() {
            found.push(Detection { class, score, bbox: [b[0] - b[2] / 2.0, b[1] - b[3] / 2.0, b[0] + b[2] / 2.0, b[1] + b[3] / 2.0] });
        }
    };
    for l in &layout.levels {
        let d = level_data(layout, l, out)?;
        let cells = l.height * l.width;
        for y in 0..l.height {
            for x in 0..l.width {
                let cell = y * l.width + x;
                match layout.kind {
                    HeadKind::Yolov5Anchor => {
                        for a in 0..l.anchors.len() {
                            stats.cells += 1;
                            let score = |k: usize| d.scores[(a * (1 + nc) + k) * cells + cell];
                            let obj = score(0);
                            if !(obj > conf) {
                                stats.skipped += 1;
                                continue;
                            }
                            let (class, p) = best((0..nc).map(|k| score(1 + k)));
                            push(v5_box(l, layout.offset, &d, a, x, y), class, obj * p);
                        }
                    }
                    HeadKind::Yolov8Dfl => {
                        stats.cells += 1;
                        if d.score_sum.is_some_and(|s| !(s[cell] > conf)) {
                            stats.skipped += 1;
                            continue;
                        }
                        let (class, p) = best((0..nc).map(|k| d.scores[k * cells + cell]));
                        if p > conf {
                            push(v8_box(l, layout.offset, &d, layout.reg_max.unwrap_or(16), x, y), class, p);
                        }
                    }
                    HeadKind::Raw => bail!("a raw head has no layout to decode"),
                }
            }
        }
    }
    Ok((nms(found, iou, max_det), stats))
}

/// Index and value of the largest score (the first on ties, as the in-graph path's argmax).
fn best(scores: impl Iterator<Item = f32>) -> (usize, f32) {
    scores.enumerate().fold((0, f32::MIN), |b, (i, x)| if x > b.1 { (i, x) } else { b })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::detect::decode::candidates;

    fn random(seed: &mut u64, n: usize, scale: f32) -> Vec<f32> {
        (0..n)
            .map(|_| {
                *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((*seed >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * scale
            })
            .collect()
    }

    fn sigmoid(v: Vec<f32>) -> Vec<f32> {
        v.into_iter().map(|x| 1.0 / (1.0 + (-x).exp())).collect()
    }

    /// The skipping path finds exactly what thresholding the dense decode and NMS find.
    #[test]
    fn skipping_detect_equals_dense_decode_then_nms() {
        let mut seed = 7;
        for kind in [HeadKind::Yolov5Anchor, HeadKind::Yolov8Dfl] {
            let nc = 3;
            let mut out = HashMap::new();
            let mut levels = Vec::new();
            for (stride, h, w) in [(8, 6, 8), (16, 3, 4)] {
                let (bc, sc) = if kind == HeadKind::Yolov5Anchor { (8, 2 * (1 + nc)) } else { (64, nc) };
                let names = (format!("boxes_s{stride}"), format!("scores_s{stride}"), format!("score_sum_s{stride}"));
                let boxes = random(&mut seed, bc * h * w, 8.0);
                let scores = sigmoid(random(&mut seed, sc * h * w, 12.0));
                let sum: Vec<f32> = (0..h * w).map(|c| (0..sc).map(|k| scores[k * h * w + c]).sum::<f32>().clamp(0.0, 1.0)).collect();
                let boxes = if kind == HeadKind::Yolov5Anchor { sigmoid(boxes) } else { boxes };
                out.insert(names.0.clone(), Tensor::f32(vec![1, bc, h, w], boxes));
                out.insert(names.1.clone(), Tensor::f32(vec![1, sc, h, w], scores));
                let score_sum = (kind == HeadKind::Yolov8Dfl).then(|| {
                    out.insert(names.2.clone(), Tensor::f32(vec![1, 1, h, w], sum));
                    names.2.clone()
                });
                let anchors = if kind == HeadKind::Yolov5Anchor { vec![[10.0, 13.0], [16.0, 30.0]] } else { vec![] };
                levels.push(Level { stride, height: h, width: w, anchors, boxes: names.0, scores: names.1, score_sum });
            }
            let layout = HeadLayout { kind, classes: nc, reg_max: (kind == HeadKind::Yolov8Dfl).then_some(16), levels, offset: [0.0, 0.0] };
            let dense = decode_dense(&layout, &out).unwrap();
            for conf in [0.05, 0.25, 0.6] {
                let expected = nms(candidates(kind, &dense, conf).unwrap(), 0.45, 300);
                let (got, stats) = detect(&layout, &out, conf, 0.45, 300).unwrap();
                assert_eq!(got, expected, "{kind:?} conf {conf}");
                assert!(!expected.is_empty() || conf > 0.5);
                if conf >= 0.25 {
                    assert!(stats.skipped > 0, "{kind:?}: nothing skipped at conf {conf}");
                }
            }
        }
    }
}
