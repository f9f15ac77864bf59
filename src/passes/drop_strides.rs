//! `drop-strides`: detection levels that cannot produce an object of the scene's size go,
//! with every node only they feed.
//!
//! Needs: `--scene` with `object_px: [smallest, largest]` (an object's larger side, input
//! pixels), a recognized YOLOv5 or YOLOv8 decode (after fold-constants).
//! Does: decides per level (stride) whether it can produce such an object:
//! - YOLOv5, by its anchors and the training assignment: a level learns an object only when
//!   both sides are within a factor `anchor_t` of one of its anchors (4.0, YOLOv5's default
//!   and `models/pdinet/loss_v5.py`'s); a level none of whose anchors admits sides within
//!   the scene's range was never taught such objects;
//! - YOLOv8, by the DFL range: a side spans at most 2 (reg_max − 1) strides.
//!
//! Where the rules cannot exclude a level (YOLOv8's coarse levels may be assigned small
//! objects), it is measured: the model runs on calibration frames and a level whose share of
//! the final in-range detections (after NMS, score ≥ `score_threshold`) is at most
//! `max_share` goes too. The level Concats lose the dropped levels' candidates, and dead
//! code elimination takes their head convolutions and the neck path only they need (in
//! YOLOv5/v8 necks the bottom-up path to the coarsest scale; the backbone's deep features stay
//! where the top-down path needs them).
//! Guarantees: the kept levels' candidates are bit-identical to the original's (their
//! cone is unchanged). Reports: what each level covers, the measurement, what went.

use crate::analysis::channels::detector_convolutions;
use crate::analysis::head::{self, HeadKind};
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::to_tensor;
use super::{Pass, PassContext};
use crate::scene::geometry::{self, Level};
use crate::scene::levels::{detection_shares, drop_levels, Measure};
use anyhow::{anyhow, bail, Result};

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// YOLOv5's anchor-matching ratio in training (hyp `anchor_t`).
    pub anchor_t: f32,
    /// Measure levels the rules keep on calibration frames.
    pub measure: bool,
    /// Calibration frames for the measurement. 32 synthetic frames held 39 detections of
    /// 0..24 px and missed the 5% YOLOv5's stride 16 carries; 128 hold over 100 (1.5 s at
    /// 256x192).
    pub frames: usize,
    /// A level with at most this share of the in-range detections is dropped: 0.5% keeps the
    /// measured agreement on in-range detections near 0.995 at worst.
    pub max_share: f64,
    /// Seed of the simulated calibration frames (when no `--calib`).
    pub seed: u64,
}

impl Default for Options {
    fn default() -> Self {
        Options { anchor_t: 4.0, measure: true, frames: 128, max_share: 0.005, seed: 0 }
    }
}

pub struct DropStrides {
    pub options: Options,
}

/// Detections at or above this score count in the measurement (YOLO's deployment default;
/// the scene's `score_threshold` overrides it).
const DEFAULT_SCORE: f32 = 0.25;

impl Pass for DropStrides {
    fn name(&self) -> &'static str {
        "drop-strides"
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let Some(scene) = cx.scene.as_ref().filter(|s| s.object_px.is_some()) else {
            return Ok(serde_json::json!({ "skipped": "the scene gives no object_px" }));
        };
        let [lo, hi] = scene.object_px.expect("checked");
        let g = super::graph_mut(model)?;
        let (_, _, levels) = geometry::levels(g)?;
        let (head, rules) = {
            let graph = Graph::build(g)?;
            let inf = infer(&graph);
            let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
            let head = head::detect(&graph, &inf, &outputs);
            let rules: Vec<(bool, String)> = match head.kind {
                HeadKind::Yolov5Anchor => v5_anchors(&graph, &inf, &levels)?.iter().map(|a| v5_rule(a, lo, hi, self.options.anchor_t)).collect(),
                HeadKind::Yolov8Dfl => levels.iter().map(|l| v8_rule(l, head.reg_max.unwrap_or(16), lo)).collect(),
                HeadKind::Raw => bail!("drop-strides needs a YOLOv5 or YOLOv8 decode in the graph; this head is raw"),
            };
            (head, rules)
        };
        let shares = if self.options.measure {
            let m = Measure { calib: cx.calib.as_deref(), frames: self.options.frames, seed: self.options.seed, size: [lo, hi], score: scene.score_threshold.unwrap_or(DEFAULT_SCORE) };
            Some(detection_shares(model, &head, &levels, &m)?)
        } else {
            None
        };
        let keep: Vec<bool> = rules
            .iter()
            .enumerate()
            .map(|(i, (can, _))| *can && shares.as_ref().is_none_or(|(s, _)| s[i] > self.options.max_share))
            .collect();
        if !keep.iter().any(|&k| k) {
            bail!("object_px [{lo}, {hi}] leaves no detection level: every stride is either unable to produce such objects or produced none on the calibration frames");
        }
        let report_levels: Vec<serde_json::Value> = levels
            .iter()
            .enumerate()
            .map(|(i, l)| {
                serde_json::json!({
                    "stride": l.stride,
                    "covers": rules[i].1,
                    "in_range_share": shares.as_ref().map(|(s, _)| s[i]),
                    "kept": keep[i],
                    "why": if !rules[i].0 { "cannot produce an object in object_px" } else if !keep[i] { "measured share at or below max_share" } else { "kept" },
                })
            })
            .collect();
        let cut = drop_levels(model, &keep, Some([lo, hi]))?;
        Ok(serde_json::json!({
            "object_px": [lo, hi],
            "levels": report_levels,
            "measured_on": shares.map(|(_, src)| src),
            "concats_cut": cut.concats,
            "constants_cut": cut.constants,
        }))
    }
}

/// Each level's anchors (w, h in pixels): the decode multiplies (2 sigmoid)^2 by a constant
/// [1, A, 1, 1, 2] downstream of the level's head convolution.
fn v5_anchors(g: &Graph, inf: &crate::ir::Inferred, levels: &[Level]) -> Result<Vec<Vec<[f32; 2]>>> {
    let convs = detector_convolutions(g);
    levels
        .iter()
        .map(|l| {
            let conv = convs
                .iter()
                .copied()
                .find(|&c| inf.shape(&g.node(c).output[0]).is_some_and(|s| s.len() == 4 && s[2] == l.height && s[3] == l.width))
                .ok_or_else(|| anyhow!("no head convolution at stride {}", l.stride))?;
            let mut seen = std::collections::HashSet::new();
            let mut stack = vec![conv];
            while let Some(i) = stack.pop() {
                if !seen.insert(i) {
                    continue;
                }
                let n = g.node(i);
                if n.op_type == "Mul" {
                    for v in &n.input {
                        let Some(t) = g.initializers.get(v.as_str()).and_then(|t| to_tensor(t).ok()) else { continue };
                        if let ([1, a, 1, 1, 2], Some(x)) = (t.shape.as_slice(), t.as_f32()) {
                            return Ok((0..*a).map(|i| [x[2 * i], x[2 * i + 1]]).collect());
                        }
                    }
                }
                if n.op_type != "Concat" {
                    stack.extend(n.output.iter().flat_map(|o| g.consumers_of(o).iter().copied()));
                }
            }
            bail!("no anchor constant [1, A, 1, 1, 2] after the stride-{} head convolution", l.stride)
        })
        .collect()
}

/// A YOLOv5 level can learn an object whose sides are within `t` of an anchor's: it is
/// needed when some anchor admits both sides ≤ `hi` with the larger one ≥ `lo`.
fn v5_rule(anchors: &[[f32; 2]], lo: f32, hi: f32, t: f32) -> (bool, String) {
    let can = anchors.iter().any(|&[aw, ah]| aw / t < hi && ah / t < hi && (aw * t > lo || ah * t > lo));
    let min = anchors.iter().map(|a| a[0].min(a[1]) / t).fold(f32::MAX, f32::min);
    let max = anchors.iter().map(|a| a[0].max(a[1]) * t).fold(0f32, f32::max);
    (can, format!("sides {min:.1}..{max:.1} px (anchors {anchors:?} within ×{t})"))
}

/// A YOLOv8 level's box sides span at most 2 (reg_max − 1) strides.
fn v8_rule(l: &Level, reg_max: usize, lo: f32) -> (bool, String) {
    let max = 2.0 * (reg_max as f32 - 1.0) * l.stride as f32;
    (lo <= max, format!("sides up to {max:.0} px (2 × {} bins × stride {})", reg_max - 1, l.stride))
}
