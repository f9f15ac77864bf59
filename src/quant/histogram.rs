//! A one-pass histogram of an activation whose range is not known in advance.
//!
//! Bins are symmetric around zero over [-R, R]; when a value falls outside, R doubles and
//! neighbouring bins merge pairwise, so calibration streams frames once instead of a min/max
//! pass followed by a histogram pass (which would double the float inference at 640x480).
//! Exact min, max, count and sum are kept beside the bins.

/// Bins across [-R, R]. 2048 is TensorRT's entropy calibration resolution; a multiple of 4
/// keeps the pairwise merge aligned with zero.
pub const BINS: usize = 2048;

#[derive(Clone, Debug)]
pub struct Histogram {
    /// Half-width of the binned range; 0 until a nonzero finite value arrives.
    pub radius: f64,
    pub counts: Vec<u64>,
    pub min: f64,
    pub max: f64,
    pub count: u64,
    pub sum: f64,
    /// NaN or infinite values seen (not binned).
    pub non_finite: u64,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram { radius: 0.0, counts: vec![0; BINS], min: f64::INFINITY, max: f64::NEG_INFINITY, count: 0, sum: 0.0, non_finite: 0 }
    }
}

/// Values binned per call at most: min, max, sum and count always see every value (the
/// extremes decide minmax ranges and carry a detector's strongest activations), the bins a
/// strided sample, which keeps a 640x480 frame's activations cheap to calibrate on.
pub const MAX_BINNED_PER_CALL: usize = 1 << 16;

impl Histogram {
    /// Adds every value to the statistics and a strided sample of them (plus the extremes)
    /// to the bins.
    pub fn add(&mut self, values: &[f32]) {
        if values.len() <= MAX_BINNED_PER_CALL {
            return self.add_all(values);
        }
        let (lo, hi, sum, finite) = match fast_stats(values) {
            Some((lo, hi, sum)) => (lo, hi, sum, values.len() as u64),
            None => values.iter().filter(|v| v.is_finite()).fold((f32::INFINITY, f32::NEG_INFINITY, 0.0f64, 0u64), |(lo, hi, s, n), &v| (lo.min(v), hi.max(v), s + v as f64, n + 1)),
        };
        let stride = values.len().div_ceil(MAX_BINNED_PER_CALL);
        let sample: Vec<f32> = values.iter().step_by(stride).copied().chain([lo, hi].into_iter().filter(|v| v.is_finite())).collect();
        let (count, sum_before, non_finite) = (self.count, self.sum, self.non_finite);
        self.add_all(&sample);
        self.count = count + finite;
        self.sum = sum_before + sum;
        self.non_finite = non_finite + (values.len() as u64 - finite);
    }

    fn add_all(&mut self, values: &[f32]) {
        let peak = values.iter().filter(|v| v.is_finite()).fold(0.0f64, |m, &v| m.max(v.abs() as f64));
        if peak > self.radius {
            self.grow_to(peak);
        }
        let width = self.bin_width();
        for &v in values {
            if !v.is_finite() {
                self.non_finite += 1;
                continue;
            }
            let v = v as f64;
            self.min = self.min.min(v);
            self.max = self.max.max(v);
            self.count += 1;
            self.sum += v;
            if width > 0.0 {
                let b = ((v + self.radius) / width) as usize;
                self.counts[b.min(BINS - 1)] += 1;
            } else {
                // All zeros so far: they sit in the bin just above zero.
                self.counts[BINS / 2] += 1;
            }
        }
    }

    /// Values in the bins (a sample of `count` for large tensors).
    pub fn binned(&self) -> u64 {
        self.counts.iter().sum()
    }

    pub fn bin_width(&self) -> f64 {
        2.0 * self.radius / BINS as f64
    }

    /// Centre of bin `b`.
    pub fn center(&self, b: usize) -> f64 {
        -self.radius + (b as f64 + 0.5) * self.bin_width()
    }

    pub fn mean(&self) -> f64 {
        if self.count == 0 { 0.0 } else { self.sum / self.count as f64 }
    }

    /// Whether any finite value was seen.
    pub fn is_empty(&self) -> bool {
        self.count == 0
    }

    fn grow_to(&mut self, peak: f64) {
        if self.radius == 0.0 {
            // First nonzero value: any zeros already counted stay in the bin above zero.
            self.radius = peak;
            return;
        }
        while self.radius < peak {
            let mut merged = vec![0u64; BINS];
            for (b, &c) in self.counts.iter().enumerate() {
                merged[BINS / 4 + b / 2] += c;
            }
            self.counts = merged;
            self.radius *= 2.0;
        }
    }
}

/// Min, max and sum in lanes the compiler vectorizes; None when a value is not finite
/// (then the caller takes the careful path).
fn fast_stats(values: &[f32]) -> Option<(f32, f32, f64)> {
    const LANES: usize = 16;
    let (mut lo, mut hi, mut sum) = ([f32::INFINITY; LANES], [f32::NEG_INFINITY; LANES], 0.0f64);
    for block in values.chunks(1 << 12) {
        let mut part = [0.0f32; LANES];
        let mut chunks = block.chunks_exact(LANES);
        for c in &mut chunks {
            for k in 0..LANES {
                lo[k] = lo[k].min(c[k]);
                hi[k] = hi[k].max(c[k]);
                part[k] += c[k];
            }
        }
        for &v in chunks.remainder() {
            lo[0] = lo[0].min(v);
            hi[0] = hi[0].max(v);
            part[0] += v;
        }
        sum += part.iter().map(|&p| p as f64).sum::<f64>();
    }
    let (lo, hi) = (lo.iter().copied().fold(f32::INFINITY, f32::min), hi.iter().copied().fold(f32::NEG_INFINITY, f32::max));
    // f32::min/max skip NaN, so a NaN shows only in the sum.
    (lo.is_finite() && hi.is_finite() && sum.is_finite()).then_some((lo, hi, sum))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growing_keeps_counts_and_order() {
        let mut h = Histogram::default();
        h.add(&[0.0, 0.5, -0.5, 1.0]);
        h.add(&[7.5, -3.0]);
        assert_eq!(h.counts.iter().sum::<u64>(), 6);
        assert!(h.radius >= 7.5);
        assert_eq!((h.min, h.max), (-3.0, 7.5));
        // Every value lies in the bin whose span holds it (a value on a bin's upper edge, as
        // the first maximum was, may sit in the bin below).
        for v in [0.0, 0.5, -0.5, 1.0, 7.5, -3.0] {
            let b = (((v + h.radius) / h.bin_width()) as usize).min(BINS - 1);
            assert!(h.counts[b] > 0 || h.counts[b - 1] > 0, "value {v} bin {b}");
        }
    }

    #[test]
    fn large_tensors_keep_exact_statistics_and_their_extremes() {
        let mut v: Vec<f32> = (0..1_000_000).map(|i| (i % 1000) as f32 / 1000.0).collect();
        v[123_457] = 50.0;
        v[7] = f32::NAN;
        let mut h = Histogram::default();
        h.add(&v);
        assert_eq!((h.count, h.non_finite, h.max), (999_999, 1, 50.0));
        assert!(h.binned() < 100_000);
        assert!(h.counts[BINS - 1] > 0, "the outlier is binned");
    }

    #[test]
    fn constant_and_non_finite_values_are_safe() {
        let mut h = Histogram::default();
        h.add(&[0.0; 16]);
        assert_eq!(h.radius, 0.0);
        h.add(&[f32::NAN, f32::INFINITY]);
        assert_eq!(h.non_finite, 2);
        assert_eq!(h.count, 16);
    }
}
