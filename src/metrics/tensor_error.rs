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
    let mut sums = ErrorSums::default();
    sums.add(reference.iter().copied(), candidate.iter().copied());
    sums.finish()
}

/// Running sums behind [`compare`], for errors accumulated over many frames without keeping
/// the frames.
#[derive(Clone, Copy, Debug, Default)]
pub struct ErrorSums {
    diff2: f64,
    ref2: f64,
    cand2: f64,
    dot: f64,
    max_abs: f64,
    non_finite: usize,
}

impl ErrorSums {
    pub fn add(&mut self, reference: impl Iterator<Item = f64>, candidate: impl Iterator<Item = f64>) {
        for (a, b) in reference.zip(candidate) {
            if !b.is_finite() && a.is_finite() {
                self.non_finite += 1;
                continue;
            }
            let d = a - b;
            self.diff2 += d * d;
            self.ref2 += a * a;
            self.cand2 += b * b;
            self.dot += a * b;
            self.max_abs = self.max_abs.max(d.abs());
        }
    }

    pub fn finish(&self) -> TensorError {
        let (diff2, ref2, cand2) = (self.diff2, self.ref2, self.cand2);
        let rel_l2 = if ref2 > 0.0 { (diff2 / ref2).sqrt() } else if diff2 == 0.0 { 0.0 } else { f64::INFINITY };
        let cosine = if ref2 > 0.0 && cand2 > 0.0 { self.dot / (ref2.sqrt() * cand2.sqrt()) } else if ref2 == cand2 { 1.0 } else { 0.0 };
        TensorError { max_abs: self.max_abs, rel_l2, cosine, non_finite: self.non_finite }
    }
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
