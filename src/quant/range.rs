//! Choosing an activation's quantization range from its histogram.
//!
//! `minmax` keeps every value; `percentile` clips the tails; `entropy` is TensorRT's KL
//! calibration (the clip threshold whose 128-level quantization loses the least information
//! about the distribution of |x|); `mse` picks the clipping that minimises the expected
//! squared error of the actual quantization grid. Every range holds zero, so zero padding
//! is exact.

use super::histogram::{Histogram, BINS};
use super::params::{ActivationType, QParams};

#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    Minmax,
    Percentile,
    Entropy,
    Mse,
}

/// Quantization levels TensorRT's entropy calibration compares against (int8's positive half).
const KL_LEVELS: usize = 128;
/// Clip candidates the `mse` search tries, geometrically from the full range down to 5% of it.
const MSE_CANDIDATES: usize = 96;
const MSE_SMALLEST_FRACTION: f64 = 0.05;

/// The range [lo, hi] (lo <= 0 <= hi) to quantize `h` with.
pub fn choose(h: &Histogram, method: Method, percentile: f64, ty: ActivationType) -> (f64, f64) {
    if h.is_empty() {
        return (0.0, 0.0);
    }
    let full = (h.min.min(0.0), h.max.max(0.0));
    if h.radius == 0.0 {
        return full;
    }
    match method {
        Method::Minmax => full,
        Method::Percentile => {
            let lo = if h.min < 0.0 { quantile(h, 1.0 - percentile / 100.0) } else { 0.0 };
            (lo.max(h.min).min(0.0), quantile(h, percentile / 100.0).min(h.max).max(0.0))
        }
        Method::Entropy => {
            let t = kl_threshold(h);
            (full.0.max(-t), full.1.min(t))
        }
        Method::Mse => mse_range(h, full, ty),
    }
}

/// The value below which a fraction `q` of the counts lie (upper edge of that bin).
fn quantile(h: &Histogram, q: f64) -> f64 {
    let target = (q.clamp(0.0, 1.0) * h.binned() as f64).ceil() as u64;
    let mut seen = 0;
    for (b, &c) in h.counts.iter().enumerate() {
        seen += c;
        if seen >= target.max(1) {
            return -h.radius + (b + 1) as f64 * h.bin_width();
        }
    }
    h.radius
}

/// TensorRT's threshold: fold the histogram onto |x|, then for every candidate number of
/// bins i >= 128 compare P (bins below i, the clipped tail added to the last) with Q (P
/// merged into 128 levels and spread back over its nonzero bins); the i with the least
/// KL(P || Q) gives the threshold.
fn kl_threshold(h: &Histogram) -> f64 {
    let half = BINS / 2;
    let abs: Vec<f64> = (0..half).map(|i| (h.counts[half + i] + h.counts[half - 1 - i]) as f64).collect();
    let width = h.bin_width();
    let last_nonzero = abs.iter().rposition(|&c| c > 0.0).unwrap_or(0) + 1;
    if last_nonzero <= KL_LEVELS {
        return last_nonzero as f64 * width;
    }
    let mut best = (f64::INFINITY, last_nonzero);
    for i in KL_LEVELS..=last_nonzero {
        let mut p: Vec<f64> = abs[..i].to_vec();
        p[i - 1] += abs[i..].iter().sum::<f64>();
        let mut q = vec![0.0; i];
        for level in 0..KL_LEVELS {
            let (start, end) = (level * i / KL_LEVELS, ((level + 1) * i / KL_LEVELS).max(level * i / KL_LEVELS + 1));
            let nonzero = abs[start..end].iter().filter(|&&c| c > 0.0).count();
            if nonzero == 0 {
                continue;
            }
            let total: f64 = abs[start..end].iter().sum();
            for b in start..end {
                if abs[b] > 0.0 {
                    q[b] = total / nonzero as f64;
                }
            }
        }
        let (sp, sq) = (p.iter().sum::<f64>(), q.iter().sum::<f64>());
        if sp <= 0.0 || sq <= 0.0 {
            continue;
        }
        let mut kl = 0.0;
        for (a, b) in p.iter().zip(&q) {
            if *a > 0.0 {
                let (a, b) = (a / sp, (b / sq).max(1e-12));
                kl += a * (a / b).ln();
            }
        }
        if kl < best.0 {
            best = (kl, i);
        }
    }
    best.1 as f64 * width
}

/// The scaled-down range with the smallest expected squared quantization error.
fn mse_range(h: &Histogram, full: (f64, f64), ty: ActivationType) -> (f64, f64) {
    let bins: Vec<(f64, f64)> = h.counts.iter().enumerate().filter(|(_, &c)| c > 0).map(|(b, &c)| (h.center(b), c as f64)).collect();
    let mut best = (f64::INFINITY, full);
    for k in 0..MSE_CANDIDATES {
        let f = MSE_SMALLEST_FRACTION.powf(k as f64 / (MSE_CANDIDATES - 1) as f64);
        let range = (full.0 * f, full.1 * f);
        let p = QParams::activation(range.0, range.1, ty);
        let err: f64 = bins.iter().map(|&(x, c)| c * (x - p.fake_quant(x)).powi(2)).sum();
        if err < best.0 {
            best = (err, range);
        }
    }
    best.1
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with_outlier() -> Histogram {
        let mut h = Histogram::default();
        // Exponentially distributed activations (mean 1, the largest near 9) and one outlier.
        let v: Vec<f32> = (0..10_000).map(|i| -(1.0 - ((i * 7919) % 10_000) as f32 / 10_000.0).ln()).collect();
        h.add(&v);
        h.add(&[100.0]);
        h
    }

    #[test]
    fn clipping_methods_ignore_a_single_outlier() {
        let h = with_outlier();
        assert_eq!(choose(&h, Method::Minmax, 99.99, ActivationType::U8), (0.0, 100.0));
        // mse weighs the outlier's clipping error (90^2) against everyone's rounding error:
        // here keeping it is right, and its expected error is never above minmax's.
        let err = |(lo, hi): (f64, f64)| {
            let p = QParams::activation(lo, hi, ActivationType::U8);
            h.counts.iter().enumerate().map(|(b, &c)| c as f64 * (h.center(b) - p.fake_quant(h.center(b))).powi(2)).sum::<f64>()
        };
        assert!(err(choose(&h, Method::Mse, 99.99, ActivationType::U8)) <= err((0.0, 100.0)));
        for m in [Method::Percentile, Method::Entropy] {
            let (lo, hi) = choose(&h, m, 99.9, ActivationType::U8);
            assert!(lo == 0.0 && (2.0..20.0).contains(&hi), "{m:?}: {lo} {hi}");
        }
    }

    #[test]
    fn ranges_hold_zero_and_are_finite_on_degenerate_input() {
        let mut h = Histogram::default();
        h.add(&[3.0; 100]);
        for m in [Method::Minmax, Method::Percentile, Method::Entropy, Method::Mse] {
            let (lo, hi) = choose(&h, m, 99.99, ActivationType::U8);
            assert!(lo <= 0.0 && hi >= 0.0 && hi.is_finite(), "{m:?}: {lo} {hi}");
        }
        assert_eq!(choose(&Histogram::default(), Method::Entropy, 99.99, ActivationType::U8), (0.0, 0.0));
    }
}
