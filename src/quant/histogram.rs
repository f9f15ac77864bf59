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
        let summary = fast_stats(values).map(|(lo, hi, sum)| (lo, hi, sum, values.len() as u64)).unwrap_or_else(|| slow_stats(values));
        self.add_summarized(values, summary);
    }

    /// [`Histogram::add`] for a tensor of `planes` equal planes (NCHW, batch 1), also returning
    /// each plane's mean, from the same pass over the values (calibration reads every
    /// convolution input for both its range and, for bias correction, its channel means).
    pub fn add_planes(&mut self, values: &[f32], planes: usize) -> Vec<f64> {
        let planes = planes.max(1);
        let plane = (values.len() / planes).max(1);
        let mut means = vec![0.0; planes];
        if values.len() <= MAX_BINNED_PER_CALL {
            for (m, chunk) in means.iter_mut().zip(values.chunks(plane)) {
                *m = chunk.iter().map(|&v| v as f64).sum::<f64>() / plane as f64;
            }
            self.add_all(values);
            return means;
        }
        let per_plane: Vec<Option<(f32, f32, f64)>> = values.chunks(plane).map(fast_stats).collect();
        for (m, (chunk, s)) in means.iter_mut().zip(values.chunks(plane).zip(&per_plane)) {
            // A plane holding NaN or Inf gets a non-finite mean, as a plain sum would give it.
            *m = s.map_or_else(|| chunk.iter().map(|&v| v as f64).sum::<f64>(), |(_, _, sum)| sum) / plane as f64;
        }
        let summary = if per_plane.iter().all(Option::is_some) {
            per_plane.iter().flatten().fold((f32::INFINITY, f32::NEG_INFINITY, 0.0f64, values.len() as u64), |(lo, hi, sum, n), &(l, h, s)| (lo.min(l), hi.max(h), sum + s, n))
        } else {
            slow_stats(values)
        };
        self.add_summarized(values, summary);
        means
    }

    /// Exact (min, max, sum, finite count) of `values` go to the statistics; a strided sample
    /// (plus the extremes) to the bins. The sample's peak is the extremes', so no pass over it
    /// is needed before binning.
    fn add_summarized(&mut self, values: &[f32], (lo, hi, sum, finite): (f32, f32, f64, u64)) {
        let extremes = [lo, hi].into_iter().filter(|v| v.is_finite());
        let peak = extremes.clone().fold(0.0f64, |m, v| m.max(v.abs() as f64));
        if peak > self.radius {
            self.grow_to(peak);
        }
        let width = self.bin_width();
        let stride = values.len().div_ceil(MAX_BINNED_PER_CALL);
        for v in values.iter().step_by(stride).copied().chain(extremes.clone()).filter(|v| v.is_finite()) {
            self.bin(v as f64, width);
        }
        for v in extremes {
            self.min = self.min.min(v as f64);
            self.max = self.max.max(v as f64);
        }
        self.count += finite;
        self.sum += sum;
        self.non_finite += values.len() as u64 - finite;
    }

    fn bin(&mut self, v: f64, width: f64) {
        if width > 0.0 {
            let b = ((v + self.radius) / width) as usize;
            self.counts[b.min(BINS - 1)] += 1;
        } else {
            // All zeros so far: they sit in the bin just above zero.
            self.counts[BINS / 2] += 1;
        }
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
            self.bin(v, width);
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

/// (min, max, sum, count) over the finite values, one by one: the path for tensors holding
/// NaN or Inf.
fn slow_stats(values: &[f32]) -> (f32, f32, f64, u64) {
    values.iter().filter(|v| v.is_finite()).fold((f32::INFINITY, f32::NEG_INFINITY, 0.0f64, 0u64), |(lo, hi, s, n), &v| (lo.min(v), hi.max(v), s + v as f64, n + 1))
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

    /// One pass for both: the same histogram as `add`, and every plane's mean.
    #[test]
    fn add_planes_matches_add_and_plane_means() {
        for len in [4 * 1000, 4 * 70_000] {
            let values: Vec<f32> = (0..len).map(|i| ((i * 7919) % 1013) as f32 / 97.0 - 3.0 + (i / (len / 4)) as f32).collect();
            let (mut a, mut b) = (Histogram::default(), Histogram::default());
            a.add(&values);
            let means = b.add_planes(&values, 4);
            assert_eq!(a.counts, b.counts, "len {len}");
            assert_eq!((a.min, a.max, a.count, a.non_finite), (b.min, b.max, b.count, b.non_finite));
            assert!((a.sum - b.sum).abs() <= 1e-6 * a.sum.abs().max(1.0), "{} vs {}", a.sum, b.sum);
            for (k, m) in means.iter().enumerate() {
                let plane = &values[k * len / 4..(k + 1) * len / 4];
                let exact = plane.iter().map(|&v| v as f64).sum::<f64>() / plane.len() as f64;
                assert!((m - exact).abs() <= 1e-5, "len {len} plane {k}: {m} vs {exact}");
            }
        }
        let mut with_nan = vec![1.0f32; 4 * 70_000];
        with_nan[5] = f32::NAN;
        let means = Histogram::default().add_planes(&with_nan, 4);
        assert!(means[0].is_nan() && means[1] == 1.0, "{means:?}");
    }

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
