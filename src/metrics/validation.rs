//! How validation decodes a detection output, and what a candidate model is scored against
//! when the frames have no labels: the reference's confident detections. `verify`, `run`,
//! `stress` and the scene passes share it, so their figures are the same computation.

use crate::analysis::head::{Head, HeadKind};
use crate::detect::{decode, nms::nms, Detection};
use crate::metrics::coco_map::Truth;
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};

/// Validation's candidate threshold (YOLO val): low, so the precision-recall curve is
/// complete; what mAP against labels is computed from, here and in `verify`.
pub const EVAL_CONF: f32 = 0.001;
/// Detections kept per frame (ultralytics' max_det).
pub const DEFAULT_MAX_DET: usize = 300;

/// NMS IoU threshold of ultralytics' validation for each head: `run` and `verify` use the same,
/// so `run`'s mAP against labels is `verify`'s.
pub fn default_iou(kind: HeadKind) -> f32 {
    if kind == HeadKind::Yolov8Dfl { 0.7 } else { 0.6 }
}

/// A reference detection counts as an object to agree on from this score (a deployment's usual cut).
pub const AGREEMENT_CONF: f32 = 0.25;
/// COCO scores at most this many detections per frame and class; truths are capped alike so
/// that a candidate identical to the reference scores 1.
const TRUTH_PER_CLASS: usize = 100;

/// The validation decode of a model's detection output: candidates at [`EVAL_CONF`], NMS.
pub fn detections(head: &Head, outputs: &[(String, Tensor)]) -> Result<Vec<Detection>> {
    let name = head.output.as_deref().ok_or_else(|| anyhow!("no detection output"))?;
    let t = &outputs.iter().find(|(n, _)| n == name).ok_or_else(|| anyhow!("output {name} missing"))?.1;
    // Validation's decode: what `run` (deploy) computes mAP from too.
    Ok(nms(decode::candidates(head.kind, t, EVAL_CONF)?, default_iou(head.kind), DEFAULT_MAX_DET))
}

/// Values of channels `range` of a detection tensor ([1,N,C] for v5, [1,C,N] for v8).
pub fn select_channels(kind: HeadKind, t: &Tensor, range: std::ops::Range<usize>) -> Vec<f64> {
    let v = t.data.to_f64();
    match kind {
        HeadKind::Yolov5Anchor => v.chunks_exact(t.shape[2]).flat_map(|row| row[range.clone()].to_vec()).collect(),
        _ => v[range.start * t.shape[2]..range.end * t.shape[2]].to_vec(),
    }
}

/// The reference's detections taken as truth when a candidate is scored against them:
/// those scoring at least AGREEMENT_CONF (capped per class), and how they were chosen.
pub fn agreement_truth(reference: &[Vec<Detection>], classes: usize) -> (Vec<Vec<Truth>>, String) {
    let confident = reference.iter().any(|ds| ds.iter().any(|d| d.score >= AGREEMENT_CONF));
    // An untrained (or very unsure) reference has no confident boxes: then every box it keeps
    // after NMS is an object to agree on, and precision and recall say how many the candidate
    // reproduces and how many it adds.
    let floor = if confident { AGREEMENT_CONF } else { EVAL_CONF };
    let how = if confident {
        format!("reference detections with score >= {AGREEMENT_CONF}")
    } else {
        format!("no reference score reaches {AGREEMENT_CONF}: all its detections after NMS")
    };
    let truth = reference
        .iter()
        .map(|ds| {
            let mut per_class = vec![0usize; classes];
            ds.iter() // sorted best first by NMS
                .filter(|d| d.score >= floor && d.class < classes)
                .filter(|d| {
                    per_class[d.class] += 1;
                    per_class[d.class] <= TRUTH_PER_CLASS
                })
                .map(|d| Truth { class: d.class, bbox: d.bbox })
                .collect()
        })
        .collect();
    (truth, how)
}
