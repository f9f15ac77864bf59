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

/// Values summarized and sampled together: 128 KiB of f32, well inside a core's L2.
const CACHE_CHUNK: usize = 1 << 15;

/// What one tensor adds to a histogram, computed without it: the pass over the values, which
/// calibration runs for several frames at once. Only [`Histogram::admit`] must take frames in
/// order (the bins depend on the order in which the range grows), and it is cheap.
#[derive(Clone, Debug)]
pub struct Summary {
    /// Extremes of the finite values (infinite when there are none).
    lo: f32,
    hi: f32,
    /// Sum of the finite values, when `everything` is false.
    sum: f64,
    finite: u64,
    total: u64,
    /// The values to bin, in order: every finite value of a small tensor, or a strided
    /// sample of a large one (its extremes are binned beside it).
    sample: Vec<f32>,
    everything: bool,
}

impl Summary {
    /// The summary of `values`, and the mean of each of `planes` equal planes (NCHW, batch 1;
    /// non-finite where a plane holds NaN or Inf, as a plain sum gives it), from one pass
    /// (calibration reads every convolution input for both its range and, for bias
    /// correction, its channel means).
    /// A large tensor goes in cache-sized chunks: each is summarized and its share of the
    /// sample copied out while it is still in cache (sampling in a second pass re-read the
    /// tensor from memory, one cache miss per sampled value).
    pub fn of(values: &[f32], planes: usize) -> (Summary, Vec<f64>) {
        let planes = planes.max(1);
        let plane = (values.len() / planes).max(1);
        let total = values.len() as u64;
        if values.len() <= MAX_BINNED_PER_CALL {
            let means = values.chunks(plane).take(planes).map(|chunk| chunk.iter().map(|&v| v as f64).sum::<f64>() / plane as f64).collect();
            let sample: Vec<f32> = values.iter().copied().filter(|v| v.is_finite()).collect();
            let (lo, hi) = sample.iter().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &v| (lo.min(v), hi.max(v)));
            return (Summary { lo, hi, sum: 0.0, finite: sample.len() as u64, total, sample, everything: true }, means);
        }
        let stride = values.len().div_ceil(MAX_BINNED_PER_CALL);
        let mut sums = vec![0.0f64; planes];
        let mut s = Summary { lo: f32::INFINITY, hi: f32::NEG_INFINITY, sum: 0.0, finite: 0, total, sample: Vec::with_capacity(values.len().div_ceil(stride)), everything: false };
        for (k, plane_values) in values.chunks(plane).enumerate() {
            for (j, chunk) in plane_values.chunks(CACHE_CHUNK).enumerate() {
                let (l, h, sum, n) = fast_stats(chunk).map_or_else(|| slow_stats(chunk), |(l, h, s)| (l, h, s, chunk.len() as u64));
                sums[k.min(planes - 1)] += if n as usize == chunk.len() { sum } else { chunk.iter().map(|&v| v as f64).sum() };
                (s.lo, s.hi, s.sum, s.finite) = (s.lo.min(l), s.hi.max(h), s.sum + sum, s.finite + n);
                let start = k * plane + j * CACHE_CHUNK;
                let mut i = start.div_ceil(stride) * stride - start;
                while i < chunk.len() {
                    if chunk[i].is_finite() {
                        s.sample.push(chunk[i]);
                    }
                    i += stride;
                }
            }
        }
        (s, sums.into_iter().map(|sum| sum / plane as f64).collect())
    }

    /// Counts of the summary's values in the bins of a histogram of range `radius`.
    pub fn bin_at(&self, radius: f64) -> Vec<u64> {
        let mut counts = vec![0u64; BINS];
        let width = 2.0 * radius / BINS as f64;
        let extremes: &[f32] = if self.everything { &[] } else { &[self.lo, self.hi] };
        for &v in self.sample.iter().chain(extremes).filter(|v| v.is_finite()) {
            if width > 0.0 {
                let b = ((v as f64 + radius) / width) as usize;
                counts[b.min(BINS - 1)] += 1;
            } else {
                // All zeros so far: they sit in the bin just above zero.
                counts[BINS / 2] += 1;
            }
        }
        counts
    }
}

/// Bins of a histogram of twice the range: bin b goes to BINS/4 + b/2.
fn merged(counts: &[u64]) -> Vec<u64> {
    let mut m = vec![0u64; BINS];
    for (b, &c) in counts.iter().enumerate() {
        m[BINS / 4 + b / 2] += c;
    }
    m
}

impl Histogram {
    /// Adds every value to the statistics and a strided sample of them (plus the extremes)
    /// to the bins.
    pub fn add(&mut self, values: &[f32]) {
        self.absorb(&Summary::of(values, 1).0);
    }

    /// Adds a tensor's summary: the range grows to its peak, then its values are binned.
    pub fn absorb(&mut self, s: &Summary) {
        let radius = self.admit(s);
        self.add_binned(radius, &s.bin_at(radius));
    }

    /// The order-dependent half of [`Histogram::absorb`], cheap: the range grows to the
    /// summary's peak and the exact statistics take it in. Returns the range its values are
    /// to be binned at ([`Summary::bin_at`]), which may happen later and elsewhere: bins
    /// merge linearly as the range doubles, so counts made at this range and merged up to a
    /// later one in [`Histogram::add_binned`] are those of binning them now.
    pub fn admit(&mut self, s: &Summary) -> f64 {
        let extremes = [s.lo, s.hi].into_iter().filter(|v| v.is_finite());
        let peak = extremes.clone().fold(0.0f64, |m, v| m.max(v.abs() as f64));
        if peak > self.radius {
            self.grow_to(peak);
        }
        if s.everything {
            for &v in &s.sample {
                self.sum += v as f64;
            }
        } else {
            self.sum += s.sum;
        }
        for v in extremes {
            self.min = self.min.min(v as f64);
            self.max = self.max.max(v as f64);
        }
        self.count += s.finite;
        self.non_finite += s.total - s.finite;
        self.radius
    }

    /// Adds counts made at `radius` (an earlier or the current range of this histogram),
    /// merged pairwise up to the current range as growing would have merged them.
    pub fn add_binned(&mut self, radius: f64, counts: &[u64]) {
        let mut counts = counts.to_vec();
        // A range of 0 held only zeros, which stay in the bin above zero at any range.
        let mut r = radius;
        while r > 0.0 && r < self.radius {
            counts = merged(&counts);
            r *= 2.0;
        }
        for (c, n) in self.counts.iter_mut().zip(counts) {
            *c += n;
        }
    }

    fn grow_to(&mut self, peak: f64) {
        if self.radius == 0.0 {
            // First nonzero value: any zeros already counted stay in the bin above zero.
            self.radius = peak;
            return;
        }
        while self.radius < peak {
            self.counts = merged(&self.counts);
            self.radius *= 2.0;
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
                // Plain comparisons compile to one minps/maxps each; `f32::min` adds NaN
                // handling that made this loop a quarter slower, and a NaN shows in the sum.
                let v = c[k];
                lo[k] = if v < lo[k] { v } else { lo[k] };
                hi[k] = if v > hi[k] { v } else { hi[k] };
                part[k] += v;
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
    // Comparisons with NaN are false, so a NaN shows only in the sum.
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
            let (summary, means) = Summary::of(&values, 4);
            b.absorb(&summary);
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
        let means = Summary::of(&with_nan, 4).1;
        assert!(means[0].is_nan() && means[1] == 1.0, "{means:?}");
    }

    /// Calibration's split: frames admitted in order, their bins made later and added in
    /// another order, give the histogram of adding them one by one.
    #[test]
    fn bins_made_after_admission_match_adding_in_order() {
        let frames: Vec<Vec<f32>> = (0..6).map(|f| (0..100_000).map(|i| (((i * 7919 + f * 31) % 1013) as f32 / 97.0 - 2.0) * (1 << f) as f32 * 0.7).collect()).collect();
        let mut sequential = Histogram::default();
        frames.iter().for_each(|f| sequential.add(f));
        let mut split = Histogram::default();
        let summaries: Vec<Summary> = frames.iter().map(|f| Summary::of(f, 4).0).collect();
        let radii: Vec<f64> = summaries.iter().map(|s| split.admit(s)).collect();
        for (s, r) in summaries.iter().zip(&radii).rev() {
            split.add_binned(*r, &s.bin_at(*r));
        }
        assert!(radii.windows(2).any(|w| w[1] > w[0]), "the range grows over the frames");
        assert_eq!(split.counts, sequential.counts);
        assert_eq!((split.radius, split.min, split.max, split.count), (sequential.radius, sequential.min, sequential.max, sequential.count));
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
