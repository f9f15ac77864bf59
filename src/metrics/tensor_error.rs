//! How far one tensor is from a reference: max abs error, relative L2, cosine similarity.

use serde::Serialize;

#[derive(Clone, Copy, Debug, Serialize, Default)]
pub struct TensorError {
    pub max_abs: f64,
    /// ||a - b|| / ||a||; 0 when both are zero.
    pub rel_l2: f64,
    /// 1 when both are zero.
    pub cosine: f64,
    /// Elements that are NaN or infinite in the candidate but finite in the reference.
    pub non_finite: usize,
}

/// Error of `candidate` against `reference` (same length, f64 accumulation).
pub fn compare(reference: &[f64], candidate: &[f64]) -> TensorError {
    let (mut diff2, mut ref2, mut cand2, mut dot, mut max_abs, mut non_finite) = (0.0, 0.0, 0.0, 0.0, 0.0f64, 0);
    for (&a, &b) in reference.iter().zip(candidate) {
        if !b.is_finite() && a.is_finite() {
            non_finite += 1;
            continue;
        }
        let d = a - b;
        diff2 += d * d;
        ref2 += a * a;
        cand2 += b * b;
        dot += a * b;
        max_abs = max_abs.max(d.abs());
    }
    let rel_l2 = if ref2 > 0.0 { (diff2 / ref2).sqrt() } else if diff2 == 0.0 { 0.0 } else { f64::INFINITY };
    let cosine = if ref2 > 0.0 && cand2 > 0.0 { dot / (ref2.sqrt() * cand2.sqrt()) } else if ref2 == cand2 { 1.0 } else { 0.0 };
    TensorError { max_abs, rel_l2, cosine, non_finite }
}

#[cfg(test)]
mod tests {
    #[test]
    fn basic() {
        let e = super::compare(&[3.0, 4.0], &[3.0, 4.0]);
        assert_eq!((e.rel_l2, e.max_abs), (0.0, 0.0));
        assert!((e.cosine - 1.0).abs() < 1e-12);
        let e = super::compare(&[3.0, 4.0], &[3.0, 4.5]);
        assert!((e.rel_l2 - 0.1).abs() < 1e-12 && e.max_abs == 0.5);
        assert_eq!(super::compare(&[1.0], &[f64::NAN]).non_finite, 1);
    }
}
