//! Single-lens degradation (the paper's Eqs. for I_hat and I_raw).
//!
//! Spatially varying blur: each region's patch, extended by the kernel radius, is convolved
//! with its PSF (FFT), weighted by W_mn and summed. W_mn is the bilinear tent centred on the
//! region: the weights sum to 1 at every pixel, so there are no seams and a constant image
//! stays constant. Borders replicate the edge pixel.
//!
//! Noise and quantization: I_raw = clamp((floor(I_hat / q) + eps) q, 1e-20, 1), with eps ~
//! N(0, sigma^2). The paper leaves the units open; we read I_hat in detector counts of a
//! `full_scale` (14-bit microbolometer: 16383), so q is a quantization step in counts and the
//! noise standard deviation is sigma q counts. q = 10 then gives a high-SNR frame (~0.1% of
//! full scale noise at sigma = 2) and q = 90 a low-SNR one (~1%), as in the paper.

use super::fft2::Fft2;
use super::rng::Rng;
use rayon::prelude::*;
use rustfft::num_complex::Complex32;

pub const FULL_SCALE_14BIT: f64 = 16383.0;

#[derive(Debug, Clone, Copy)]
pub struct NoiseModel {
    pub q: f64,
    pub sigma: f64,
    pub full_scale: f64,
}

/// Precomputed spectra of every region's PSF for one frame size: build once, degrade many frames.
pub struct SpatialBlur {
    h: usize,
    w: usize,
    rows: usize,
    cols: usize,
    radius: usize,
    fft: Fft2,
    spectra: Vec<Vec<Complex32>>,
}

/// Region centres along one axis.
fn centres(n: usize, size: usize) -> Vec<f64> {
    (0..n).map(|i| (i as f64 + 0.5) * size as f64 / n as f64).collect()
}

/// Tent weight of region i at pixel coordinate x (pixel centres at x + 0.5).
fn tent(c: &[f64], i: usize, x: f64) -> f64 {
    let x = x + 0.5;
    if (i == 0 && x <= c[0]) || (i == c.len() - 1 && x >= c[i]) {
        return 1.0;
    }
    if x < c[i] {
        if i == 0 { return 1.0 }
        ((x - c[i - 1]) / (c[i] - c[i - 1])).clamp(0.0, 1.0)
    } else {
        if i + 1 >= c.len() { return 1.0 }
        ((c[i + 1] - x) / (c[i + 1] - c[i])).clamp(0.0, 1.0)
    }
}

/// Output rectangle [lo, hi) where region i's weight is non-zero.
fn support(c: &[f64], i: usize, size: usize) -> (usize, usize) {
    let lo = if i == 0 { 0 } else { c[i - 1].floor() as usize };
    let hi = if i + 1 == c.len() { size } else { (c[i + 1].ceil() as usize).min(size) };
    (lo, hi)
}

fn nice_size(n: usize) -> usize {
    (n..).find(|&m| { let mut x = m; for p in [2, 3, 5] { while x % p == 0 { x /= p } } x == 1 }).expect("exists")
}

impl SpatialBlur {
    /// `kernels[r * cols + c]` is the k x k PSF of region (r, c), k odd.
    pub fn new(kernels: &[Vec<f32>], k: usize, rows: usize, cols: usize, h: usize, w: usize) -> SpatialBlur {
        let radius = k / 2;
        let (cy, cx) = (centres(rows, h), centres(cols, w));
        let max_tile = |c: &[f64], size: usize| (0..c.len()).map(|i| { let (a, b) = support(c, i, size); b - a }).max().unwrap_or(1);
        let (th, tw) = (nice_size(max_tile(&cy, h) + 2 * radius), nice_size(max_tile(&cx, w) + 2 * radius));
        let fft = Fft2::new(th, tw);
        let spectra = kernels
            .par_iter()
            .map(|kern| {
                // Kernel centre at (0, 0), wrapped: the FFT product is then a 'same' convolution.
                let mut buf = vec![Complex32::default(); th * tw];
                for y in 0..k {
                    for x in 0..k {
                        let (yy, xx) = ((y + th - radius) % th, (x + tw - radius) % tw);
                        buf[yy * tw + xx] = Complex32::new(kern[y * k + x], 0.0);
                    }
                }
                let mut tmp = vec![Complex32::default(); th * tw];
                fft.forward(&mut buf, &mut tmp);
                buf
            })
            .collect();
        SpatialBlur { h, w, rows, cols, radius, fft, spectra }
    }

    /// I_hat = sum_mn W_mn (patch_mn * K_mn), `img` row-major h x w.
    pub fn apply(&self, img: &[f32]) -> Vec<f32> {
        let (h, w, r) = (self.h, self.w, self.radius as i64);
        let (cy, cx) = (centres(self.rows, h), centres(self.cols, w));
        let (th, tw) = (self.fft.h, self.fft.w);
        let tiles: Vec<(usize, usize, usize, usize, Vec<f32>)> = (0..self.rows * self.cols)
            .into_par_iter()
            .map(|i| {
                let (m, n) = (i / self.cols, i % self.cols);
                let ((y0, y1), (x0, x1)) = (support(&cy, m, h), support(&cx, n, w));
                let mut buf = vec![Complex32::default(); th * tw];
                for ty in 0..(y1 - y0) + 2 * r as usize {
                    let sy = (y0 as i64 + ty as i64 - r).clamp(0, h as i64 - 1) as usize;
                    for tx in 0..(x1 - x0) + 2 * r as usize {
                        let sx = (x0 as i64 + tx as i64 - r).clamp(0, w as i64 - 1) as usize;
                        buf[ty * tw + tx] = Complex32::new(img[sy * w + sx], 0.0);
                    }
                }
                let mut tmp = vec![Complex32::default(); th * tw];
                self.fft.forward(&mut buf, &mut tmp);
                for (b, k) in buf.iter_mut().zip(&self.spectra[i]) {
                    *b *= k;
                }
                self.fft.inverse(&mut buf, &mut tmp);
                let (wy, wx): (Vec<f64>, Vec<f64>) = ((y0..y1).map(|y| tent(&cy, m, y as f64)).collect(), (x0..x1).map(|x| tent(&cx, n, x as f64)).collect());
                let mut out = Vec::with_capacity((y1 - y0) * (x1 - x0));
                for (yy, &a) in wy.iter().enumerate() {
                    for (xx, &b) in wx.iter().enumerate() {
                        out.push(buf[(yy + r as usize) * tw + xx + r as usize].re * (a * b) as f32);
                    }
                }
                (y0, y1, x0, x1, out)
            })
            .collect();
        let mut acc = vec![0f32; h * w];
        for (y0, y1, x0, x1, t) in tiles {
            let tw_ = x1 - x0;
            for y in y0..y1 {
                let row = &t[(y - y0) * tw_..(y - y0 + 1) * tw_];
                for (a, v) in acc[y * w + x0..y * w + x1].iter_mut().zip(row) {
                    *a += v;
                }
            }
        }
        acc
    }
}

/// The noise and quantization model, in place; values in [0, 1] of `full_scale` counts.
pub fn add_noise(img: &mut [f32], m: &NoiseModel, rng: &mut Rng) {
    for v in img.iter_mut() {
        let counts = *v as f64 * m.full_scale;
        let raw = ((counts / m.q).floor() + m.sigma * rng.normal()) * m.q;
        *v = (raw / m.full_scale).clamp(1e-20, 1.0) as f32;
    }
}

/// Peak signal-to-noise ratio in dB for signals in [0, 1].
pub fn psnr(clean: &[f32], noisy: &[f32]) -> f64 {
    let mse: f64 = clean.iter().zip(noisy).map(|(&a, &b)| (a as f64 - b as f64).powi(2)).sum::<f64>() / clean.len() as f64;
    if mse == 0.0 { f64::INFINITY } else { 10.0 * (1.0 / mse).log10() }
}
