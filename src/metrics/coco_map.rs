//! COCO-style mAP, computed the way pycocotools' COCOeval does for bounding boxes
//! (area range "all", 100 detections per image and class, IoU 0.50:0.05:0.95, 101 recall
//! points), so numbers here and in Python agree (tested to 1e-3).

use crate::detect::Detection;
use serde::Serialize;

/// Detections kept per image and class, as COCOeval's maxDets[-1].
const MAX_DETS: usize = 100;

#[derive(Clone, Debug, Serialize)]
pub struct MapResult {
    /// AP at IoU 0.5, averaged over classes with ground truth.
    pub map50: f64,
    /// AP averaged over IoU 0.50:0.05:0.95 and classes with ground truth.
    pub map50_95: f64,
    /// Per class AP@0.5:0.95; `None` where the class has no ground truth.
    pub per_class: Vec<Option<f64>>,
}

/// A ground-truth box: class and xyxy pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Truth {
    pub class: usize,
    pub bbox: [f32; 4],
}

fn iou_thresholds() -> [f64; 10] {
    std::array::from_fn(|i| 0.5 + i as f64 * 0.05) // np.linspace(.5, .95, 10)
}

fn recall_thresholds() -> Vec<f64> {
    (0..=100).map(|i| if i == 100 { 1.0 } else { i as f64 * 0.01 }).collect() // np.linspace(0, 1, 101)
}

/// COCO's bbox IoU on xywh in double precision.
fn iou(d: &[f32; 4], g: &[f32; 4]) -> f64 {
    let (dx, dy, dw, dh) = (d[0] as f64, d[1] as f64, (d[2] - d[0]) as f64, (d[3] - d[1]) as f64);
    let (gx, gy, gw, gh) = (g[0] as f64, g[1] as f64, (g[2] - g[0]) as f64, (g[3] - g[1]) as f64);
    let w = (dx + dw).min(gx + gw) - dx.max(gx);
    let h = (dy + dh).min(gy + gh) - dy.max(gy);
    if w <= 0.0 || h <= 0.0 {
        return 0.0;
    }
    let inter = w * h;
    inter / (dw * dh + gw * gh - inter)
}

/// `truths[i]` and `detections[i]` belong to image i.
pub fn coco_map(truths: &[Vec<Truth>], detections: &[Vec<Detection>], num_classes: usize) -> MapResult {
    let thresholds = iou_thresholds();
    let recalls = recall_thresholds();
    // precision[t][c] = 101 recall-point curve, or None where class c has no ground truth.
    let mut ap = vec![vec![None::<f64>; num_classes]; thresholds.len()];
    let mut ap50 = vec![None::<f64>; num_classes];
    for c in 0..num_classes {
        let mut npig = 0usize;
        // (score, matched per threshold) of every kept detection, image by image.
        let mut scored: Vec<(f32, [bool; 10])> = Vec::new();
        let mut any = false;
        for (gts, dts) in truths.iter().zip(detections) {
            let g: Vec<&Truth> = gts.iter().filter(|t| t.class == c).collect();
            let mut d: Vec<&Detection> = dts.iter().filter(|x| x.class == c).collect();
            if g.is_empty() && d.is_empty() {
                continue;
            }
            any = true;
            npig += g.len();
            d.sort_by(|a, b| b.score.total_cmp(&a.score)); // stable, like kind='mergesort'
            d.truncate(MAX_DETS);
            let mut gt_taken = vec![[false; 10]; g.len()];
            for det in &d {
                let mut matched = [false; 10];
                for (ti, &t) in thresholds.iter().enumerate() {
                    let mut best = t.min(1.0 - 1e-10);
                    let mut m = None;
                    for (gi, gt) in g.iter().enumerate() {
                        if gt_taken[gi][ti] {
                            continue;
                        }
                        let v = iou(&det.bbox, &gt.bbox);
                        if v < best {
                            continue;
                        }
                        best = v;
                        m = Some(gi);
                    }
                    if let Some(gi) = m {
                        gt_taken[gi][ti] = true;
                        matched[ti] = true;
                    }
                }
                scored.push((det.score, matched));
            }
        }
        if !any || npig == 0 {
            continue; // COCOeval leaves such classes at -1: excluded from the mean
        }
        scored.sort_by(|a, b| b.0.total_cmp(&a.0));
        for (ti, _) in thresholds.iter().enumerate() {
            let (mut tp, mut fp) = (0usize, 0usize);
            let mut rc = Vec::with_capacity(scored.len());
            let mut pr = Vec::with_capacity(scored.len());
            for s in &scored {
                if s.1[ti] { tp += 1 } else { fp += 1 }
                rc.push(tp as f64 / npig as f64);
                pr.push(tp as f64 / ((tp + fp) as f64 + f64::EPSILON)); // np.spacing(1)
            }
            for i in (1..pr.len()).rev() {
                if pr[i] > pr[i - 1] {
                    pr[i - 1] = pr[i];
                }
            }
            let q: f64 = recalls
                .iter()
                .map(|&r| {
                    let pi = rc.partition_point(|&x| x < r); // searchsorted side='left'
                    pr.get(pi).copied().unwrap_or(0.0)
                })
                .sum::<f64>()
                / recalls.len() as f64;
            ap[ti][c] = Some(q);
            if ti == 0 {
                ap50[c] = Some(q);
            }
        }
    }
    let mean = |v: &[Option<f64>]| {
        let xs: Vec<f64> = v.iter().flatten().copied().collect();
        if xs.is_empty() { 0.0 } else { xs.iter().sum::<f64>() / xs.len() as f64 }
    };
    let per_class: Vec<Option<f64>> = (0..num_classes)
        .map(|c| {
            let xs: Vec<f64> = ap.iter().filter_map(|row| row[c]).collect();
            (!xs.is_empty()).then(|| xs.iter().sum::<f64>() / xs.len() as f64)
        })
        .collect();
    let all: Vec<Option<f64>> = ap.iter().flatten().copied().collect();
    MapResult { map50: mean(&ap50), map50_95: mean(&all), per_class }
}
