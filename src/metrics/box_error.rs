//! How far a candidate's boxes sit from the reference's, as a fraction of each box's size.
//!
//! A rel L2 over a decoded head's box rows is measured against their pixel coordinates, which
//! every anchor carries whether it sees an object or not: a box off by a fifth of its width
//! moves it by a few percent of that norm, and mAP@0.5:0.95 (which counts a box only at
//! IoU 0.5, 0.55, ... 0.95) loses most of its points there. This measure divides each side's
//! error by the reference box's own width or height and weights each anchor by the reference's
//! confidence in it, so that only the boxes a detector reports count, each at its scale.

use crate::analysis::head::HeadKind;
use crate::tensor::Tensor;

/// Box sides below this many pixels count as this many: a degenerate reference box does not
/// turn a sub-pixel error into a large one.
const MIN_SIDE: f64 = 1.0;

/// Confidence-weighted sums over frames.
#[derive(Clone, Debug, Default)]
pub struct BoxErrorSums {
    weighted: f64,
    weight: f64,
}

impl BoxErrorSums {
    /// Adds one frame's decoded outputs (YOLOv5 [1, N, 5+nc] rows, YOLOv8 [1, 4+nc, N]
    /// columns; boxes as cx, cy, w, h). Other shapes, and heads without an in-graph decode,
    /// add nothing. A candidate side that is not finite counts as an error of one box side.
    pub fn add(&mut self, kind: HeadKind, reference: &Tensor, candidate: &Tensor) {
        if reference.shape != candidate.shape || reference.shape.len() != 3 {
            return;
        }
        let (a, b) = (reference.data.to_f64(), candidate.data.to_f64());
        let (rows, cols) = (reference.shape[1], reference.shape[2]);
        // Anchors, value count per anchor, first class value, and value c of anchor i.
        type At = Box<dyn Fn(&[f64], usize, usize) -> f64>;
        let (n, channels, first_class, at): (usize, usize, usize, At) = match kind {
            HeadKind::Yolov5Anchor if cols > 5 => (rows, cols, 5, Box::new(move |v, c, i| v[i * cols + c])),
            HeadKind::Yolov8Dfl if rows > 4 => (cols, rows, 4, Box::new(move |v, c, i| v[c * cols + i])),
            _ => return,
        };
        for i in 0..n {
            let best = (first_class..channels).map(|c| at(&a, c, i)).fold(0.0, f64::max);
            // YOLOv5 scores a box by objectness times its best class; YOLOv8 by the class.
            let w = if kind == HeadKind::Yolov5Anchor { at(&a, 4, i) * best } else { best };
            if !(w > 0.0) || !w.is_finite() {
                continue;
            }
            let sides = [at(&a, 2, i).max(MIN_SIDE), at(&a, 3, i).max(MIN_SIDE)];
            let mut e = 0.0;
            for c in 0..4 {
                let d = (at(&b, c, i) - at(&a, c, i)) / sides[c % 2];
                e += if d.is_finite() { d * d } else { 1.0 };
            }
            self.weighted += w * e / 4.0;
            self.weight += w;
        }
    }

    /// Root of the weighted mean square: 0.1 when every confident box is off by a tenth of its
    /// side on each of its four values. 0 when no anchor had any confidence.
    pub fn finish(&self) -> f64 {
        if self.weight > 0.0 { (self.weighted / self.weight).sqrt() } else { 0.0 }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A YOLOv8 output with one box per anchor (cx, cy, w, h) and its single class score.
    fn v8(boxes: &[[f32; 4]], scores: &[f32]) -> Tensor {
        let n = boxes.len();
        let mut v = vec![0.0; 5 * n];
        for (i, b) in boxes.iter().enumerate() {
            for c in 0..4 {
                v[c * n + i] = b[c];
            }
            v[4 * n + i] = scores[i];
        }
        Tensor::f32(vec![1, 5, n], v)
    }

    fn error(kind: HeadKind, a: &Tensor, b: &Tensor) -> f64 {
        let mut s = BoxErrorSums::default();
        s.add(kind, a, b);
        s.finish()
    }

    #[test]
    fn the_same_relative_shift_costs_the_same_at_any_size() {
        let a = v8(&[[100.0, 100.0, 10.0, 20.0], [200.0, 100.0, 80.0, 160.0]], &[0.9, 0.0]);
        let small = v8(&[[101.0, 100.0, 10.0, 20.0], [200.0, 100.0, 80.0, 160.0]], &[0.9, 0.0]);
        let a2 = v8(&[[100.0, 100.0, 10.0, 20.0], [200.0, 100.0, 80.0, 160.0]], &[0.0, 0.9]);
        let large = v8(&[[100.0, 100.0, 10.0, 20.0], [208.0, 100.0, 80.0, 160.0]], &[0.0, 0.9]);
        // A tenth of the width on one of four values: sqrt(0.01 / 4).
        assert!((error(HeadKind::Yolov8Dfl, &a, &small) - 0.05).abs() < 1e-9);
        assert!((error(HeadKind::Yolov8Dfl, &a2, &large) - 0.05).abs() < 1e-9);
        assert_eq!(error(HeadKind::Yolov8Dfl, &a, &a), 0.0);
    }

    #[test]
    fn anchors_the_reference_does_not_see_do_not_count() {
        let a = v8(&[[100.0, 100.0, 10.0, 20.0], [200.0, 100.0, 80.0, 160.0]], &[0.5, 0.0]);
        let b = v8(&[[100.0, 100.0, 10.0, 20.0], [900.0, 0.0, 1.0, 1.0]], &[0.5, 0.0]);
        assert_eq!(error(HeadKind::Yolov8Dfl, &a, &b), 0.0);
        let nan = v8(&[[f32::NAN, 100.0, 10.0, 20.0], [200.0, 100.0, 80.0, 160.0]], &[0.5, 0.0]);
        assert!((error(HeadKind::Yolov8Dfl, &a, &nan) - 0.5).abs() < 1e-9);
    }

    #[test]
    fn yolov5_rows_weigh_objectness_times_class() {
        // Rows of (cx, cy, w, h, obj, class): the second row's box is off, but its objectness is 0.
        let a = Tensor::f32(vec![1, 2, 6], vec![50.0, 50.0, 20.0, 20.0, 0.8, 0.5, 10.0, 10.0, 4.0, 4.0, 0.0, 1.0]);
        let b = Tensor::f32(vec![1, 2, 6], vec![50.0, 52.0, 20.0, 20.0, 0.8, 0.5, 30.0, 10.0, 4.0, 4.0, 0.0, 1.0]);
        assert!((error(HeadKind::Yolov5Anchor, &a, &b) - 0.05).abs() < 1e-9);
        assert_eq!(error(HeadKind::Raw, &a, &b), 0.0);
    }
}
