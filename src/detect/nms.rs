//! Class-aware non-maximum suppression: boxes of different classes never suppress each other.

use super::{iou, Detection};

/// Keeps the best-scoring boxes, dropping any box overlapping a kept one of its class by more
/// than `iou_threshold`; at most `max_det` survive, best first.
pub fn nms(mut dets: Vec<Detection>, iou_threshold: f32, max_det: usize) -> Vec<Detection> {
    dets.sort_by(|a, b| b.score.total_cmp(&a.score));
    let mut kept: Vec<Detection> = Vec::new();
    for d in dets {
        if kept.len() >= max_det {
            break;
        }
        if kept.iter().all(|k| k.class != d.class || iou(&k.bbox, &d.bbox) <= iou_threshold) {
            kept.push(d);
        }
    }
    kept
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn suppresses_within_class_only() {
        let d = |class, score, x| Detection { class, score, bbox: [x, 0.0, x + 10.0, 10.0] };
        let kept = nms(vec![d(0, 0.9, 0.0), d(0, 0.8, 1.0), d(1, 0.7, 1.0), d(0, 0.6, 50.0)], 0.5, 300);
        let scores: Vec<f32> = kept.iter().map(|k| k.score).collect();
        assert_eq!(scores, vec![0.9, 0.7, 0.6]);
    }
}
