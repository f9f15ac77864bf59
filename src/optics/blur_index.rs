//! The PSF-aware blur-index map: per region, the energy centroid of its PSF and the RMS
//! radius of energy around it give one blur factor; factors are min-max normalized to [0, 1]
//! on the grid, and upsampled bilinearly to the feature size exactly as ONNX Resize (linear,
//! half_pixel) computes it in ONNX Runtime.

use super::blur_map::BlurMap;
use serde::Serialize;

#[derive(Debug, Clone, Copy, Serialize)]
pub struct SpotStats {
    /// Energy centroid, pixels from the kernel centre.
    pub centroid: [f64; 2],
    /// RMS radius of energy around the centroid, pixels.
    pub rms_radius: f64,
}

pub fn spot_stats(kernel: &[f32], k: usize) -> SpotStats {
    let c = (k / 2) as f64;
    let (mut s, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for (i, &v) in kernel.iter().enumerate() {
        let (x, y) = ((i % k) as f64 - c, (i / k) as f64 - c);
        s += v as f64;
        sx += v as f64 * x;
        sy += v as f64 * y;
    }
    let (cx, cy) = (sx / s, sy / s);
    let r2: f64 = kernel.iter().enumerate().map(|(i, &v)| v as f64 * (((i % k) as f64 - c - cx).powi(2) + ((i / k) as f64 - c - cy).powi(2))).sum::<f64>() / s;
    SpotStats { centroid: [cx, cy], rms_radius: r2.sqrt() }
}

/// Min-max normalized RMS radii, as the paper does, with one guard: the range is taken as at
/// least `FLAT_FIELD_FRACTION` of the smallest radius. Without it a near diffraction-limited
/// camera, whose radii differ by a few hundredths of a pixel, would get the same 0-to-1 map
/// as a single lens whose corners are twice as blurred, and the gates would swing on noise.
pub fn blur_map(stats: &[SpotStats], rows: usize, cols: usize) -> BlurMap {
    let r: Vec<f64> = stats.iter().map(|s| s.rms_radius).collect();
    let (lo, hi) = r.iter().fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let range = (hi - lo).max(FLAT_FIELD_FRACTION * lo).max(1e-12);
    let values = r.iter().map(|&v| ((v - lo) / range) as f32).collect();
    BlurMap { rows, cols, values }
}

/// Radii spread below half the axial spot size counts as a flat field (see `blur_map`).
pub const FLAT_FIELD_FRACTION: f64 = 0.5;

/// Bilinear resize of a row-major `ih x iw` map to `oh x ow`, with ONNX Resize's
/// `half_pixel` coordinates and ORT's f32 arithmetic (scale = out / in, source coordinate
/// clamped to the input).
pub fn resize_half_pixel(src: &[f32], ih: usize, iw: usize, oh: usize, ow: usize) -> Vec<f32> {
    let axis = |o: usize, i: usize| -> Vec<(usize, usize, f32)> {
        let scale = o as f32 / i as f32;
        (0..o)
            .map(|x| {
                let s = ((x as f32 + 0.5) / scale - 0.5).clamp(0.0, (i - 1) as f32);
                let x0 = s.floor() as usize;
                let x1 = (x0 + 1).min(i - 1);
                (x0, x1, s - x0 as f32)
            })
            .collect()
    };
    let (ys, xs) = (axis(oh, ih), axis(ow, iw));
    let mut out = Vec::with_capacity(oh * ow);
    for &(y0, y1, fy) in &ys {
        for &(x0, x1, fx) in &xs {
            let top = src[y0 * iw + x0] * (1.0 - fx) + src[y0 * iw + x1] * fx;
            let bottom = src[y1 * iw + x0] * (1.0 - fx) + src[y1 * iw + x1] * fx;
            out.push(top * (1.0 - fy) + bottom * fy);
        }
    }
    out
}
