//! How much a detector's detections inside an ROI depend on what lies outside it, measured on
//! the full model before anything is cropped: its detections on frames, against its detections
//! on the same frames with every pixel outside the ROI taken from the next frame. A crop never
//! sees those pixels. Where the full model's ROI detections move with them, a crop (halos and
//! trained estimates included, which can only estimate them from the ROI) agrees with it only
//! as far as such an estimate allows; where they do not, the crop's edge is the whole problem.
//! On the trained models it singles out the tiny one, the only one whose crop stays far from
//! the full model (README, *What a crop cannot see*).

use super::Roi;
use crate::analysis::head::HeadKind;
use crate::ir::{infer, Graph};
use crate::metrics::coco_map::coco_map;
use crate::onnx::proto::ModelProto;
use crate::runtime::{self, Engine};
use crate::tensor::Tensor;
use crate::metrics::validation::{agreement_truth, detections};
use anyhow::{anyhow, bail, Result};
use serde::Serialize;
use std::path::Path;

/// Frames the measurement runs on (each twice). Its unit is a class's AP over a few boxes:
/// with 64 frames (64-107 reference boxes on the trained 256x192 models) the v8's agreement
/// moved from 0.995 to 0.950 between two frame sources; with 128 (129-209 boxes) 0.996 / 0.967.
/// 256 runs of the full-size v5 at 640x480 take about 25 s on 2 cores.
pub const FRAMES: usize = 128;

#[derive(Serialize, Debug, Clone)]
pub struct ContextDependence {
    pub frames: usize,
    /// Confident detections of the full model inside the ROI, at least `margin` px from its edges.
    pub reference_boxes: usize,
    pub margin: usize,
    /// mAP@0.5:0.95 (and @0.5) of the detections with the outside swapped against those without.
    pub agreement: f64,
    pub agreement50: f64,
}

/// Measures `model` (lossless, one image input) on `n` frames of `folder` (or simulated ones)
/// for the ROI `roi`; None when it has no decoded YOLOv5 or YOLOv8 output to compare.
pub fn measure(model: &ModelProto, roi: Roi, folder: Option<&Path>, n: usize, seed: u64, threads: usize) -> Result<Option<ContextDependence>> {
    if n < 2 {
        bail!("the ROI's context dependence swaps the outside between frames: it needs at least 2");
    }
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let head = crate::inspect::inspect(model)?.head;
    if head.kind == HeadKind::Raw || head.output.is_none() {
        return Ok(None);
    }
    let (_, _, levels) = super::geometry::levels(g)?;
    let margin = levels.iter().map(|l| l.stride).max().unwrap_or(0);
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let (feeds, _) = crate::calib_frames::image_feeds(&graph, &inf, folder, n, seed)?;
    let mut rt = runtime::load(Engine::Ort, model, &feeds[0], threads)?;
    let inside = |ds: Vec<crate::detect::Detection>| -> Vec<_> { ds.into_iter().filter(|d| roi.contains(&d.bbox, margin as f32)).collect() };
    let (mut own, mut swapped) = (Vec::new(), Vec::new());
    for (i, feed) in feeds.iter().enumerate() {
        let other = &feeds[(i + 1) % feeds.len()];
        own.push(inside(detections(&head, &rt.run(feed)?)?));
        let mixed: Vec<(String, Tensor)> = feed.iter().zip(other).map(|((n, t), (_, o))| Ok((n.clone(), if t.shape.len() == 4 { outside_from(t, o, roi)? } else { t.clone() }))).collect::<Result<_>>()?;
        swapped.push(inside(detections(&head, &rt.run(&mixed)?)?));
    }
    let classes = head.classes.unwrap_or(1).max(1);
    let (truth, _) = agreement_truth(&own, classes);
    let m = coco_map(&truth, &swapped, classes);
    Ok(Some(ContextDependence { frames: feeds.len(), reference_boxes: truth.iter().map(Vec::len).sum(), margin, agreement: m.map50_95, agreement50: m.map50 }))
}

/// `t` ([N, C, H, W]) with every pixel outside `roi` taken from `other`.
fn outside_from(t: &Tensor, other: &Tensor, roi: Roi) -> Result<Tensor> {
    let (a, b) = (t.as_f32().ok_or_else(|| anyhow!("image is not float"))?, other.as_f32().ok_or_else(|| anyhow!("image is not float"))?);
    if t.shape != other.shape || a.len() != b.len() {
        bail!("frames of shapes {:?} and {:?} cannot be mixed", t.shape, other.shape);
    }
    let (h, w) = (t.shape[2], t.shape[3]);
    let mut v = b.to_vec();
    for (plane, src) in v.chunks_exact_mut(h * w).zip(a.chunks_exact(h * w)) {
        for y in roi.y..(roi.y + roi.h).min(h) {
            let (x0, x1) = (y * w + roi.x, y * w + (roi.x + roi.w).min(w));
            plane[x0..x1].copy_from_slice(&src[x0..x1]);
        }
    }
    Ok(Tensor::f32(t.shape.clone(), v))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_the_outside_comes_from_the_other_frame() {
        let t = Tensor::f32(vec![1, 1, 4, 5], (0..20).map(|v| v as f32).collect());
        let o = Tensor::f32(vec![1, 1, 4, 5], vec![-1.0; 20]);
        let m = outside_from(&t, &o, Roi { x: 1, y: 2, w: 3, h: 2 }).unwrap();
        let v = m.as_f32().unwrap();
        for y in 0..4 {
            for x in 0..5 {
                let inside = (2..4).contains(&y) && (1..4).contains(&x);
                assert_eq!(v[y * 5 + x], if inside { (y * 5 + x) as f32 } else { -1.0 }, "({x}, {y})");
            }
        }
    }
}
