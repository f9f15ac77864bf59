//! 2-D complex FFTs on row-major buffers (rows, then a transpose, then rows again).
//!
//! The forward transform leaves the spectrum transposed ([W][H]); pointwise products between
//! spectra made the same way do not care, and the inverse transposes back. One transpose
//! saved per direction matters at 48 tiles a frame.

use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};
use std::sync::Arc;

pub struct Fft2 {
    pub h: usize,
    pub w: usize,
    fw: Arc<dyn Fft<f32>>,
    fh: Arc<dyn Fft<f32>>,
    iw: Arc<dyn Fft<f32>>,
    ih: Arc<dyn Fft<f32>>,
}

impl Fft2 {
    pub fn new(h: usize, w: usize) -> Fft2 {
        let mut p = FftPlanner::new();
        Fft2 { h, w, fw: p.plan_fft_forward(w), fh: p.plan_fft_forward(h), iw: p.plan_fft_inverse(w), ih: p.plan_fft_inverse(h) }
    }

    /// In place: `buf` is [h][w] in, spectrum [w][h] out (`tmp` same size, scratch).
    pub fn forward(&self, buf: &mut [Complex32], tmp: &mut [Complex32]) {
        self.fw.process(buf);
        transpose(buf, tmp, self.h, self.w);
        self.fh.process(tmp);
        buf.copy_from_slice(tmp);
    }

    /// In place: spectrum [w][h] in, [h][w] out, scaled by 1/(h w).
    pub fn inverse(&self, buf: &mut [Complex32], tmp: &mut [Complex32]) {
        self.ih.process(buf);
        transpose(buf, tmp, self.w, self.h);
        self.iw.process(tmp);
        let s = 1.0 / (self.h * self.w) as f32;
        for (b, t) in buf.iter_mut().zip(tmp.iter()) {
            *b = t * s;
        }
    }
}

/// `src` is [rows][cols]; `dst` becomes [cols][rows].
fn transpose(src: &[Complex32], dst: &mut [Complex32], rows: usize, cols: usize) {
    const B: usize = 16; // cache blocking
    for r0 in (0..rows).step_by(B) {
        for c0 in (0..cols).step_by(B) {
            for r in r0..(r0 + B).min(rows) {
                for c in c0..(c0 + B).min(cols) {
                    dst[c * rows + r] = src[r * cols + c];
                }
            }
        }
    }
}

/// Centred 2-D FFT magnitude squared helper for PSFs: |F{field}|^2 with the zero frequency
/// moved to the centre ([h][w] in and out).
pub fn power_spectrum_centred(field: &mut [Complex32], fft: &Fft2) -> Vec<f32> {
    let mut tmp = vec![Complex32::default(); field.len()];
    fft.forward(field, &mut tmp);
    // field is now [w][h]; undo the transpose while shifting.
    let (h, w) = (fft.h, fft.w);
    let mut out = vec![0.0f32; h * w];
    for x in 0..w {
        for y in 0..h {
            let v = field[x * h + y];
            out[((y + h / 2) % h) * w + (x + w / 2) % w] = v.norm_sqr();
        }
    }
    out
}
