//! Scalar-diffraction PSFs: PSF = |F{A e^{i 2 pi W / lambda}}|^2 per wavelength, averaged over
//! the band, binned to detector pixels, one kernel per field region.
//!
//! Sampling: the pupil diameter spans `PUPIL_SAMPLES` samples; an FFT of size M gives focal
//! plane samples of lambda F# P / M. M is chosen per wavelength so that every wavelength lands
//! on (nearly) the same grid of pixel/OVERSAMPLE, and each sample is then assigned to the
//! detector pixel containing its position.

use super::fft2::{power_spectrum_centred, Fft2};
use super::lens::{FieldAberrations, Lens};
use rayon::prelude::*;
use rustfft::num_complex::Complex32;
use serde::Serialize;

/// Samples across the pupil diameter: enough to resolve several waves of aberration.
pub const PUPIL_SAMPLES: usize = 64;
/// Focal-plane samples per detector pixel before binning (odd: pixels centre on a sample).
pub const OVERSAMPLE: usize = 5;

/// Wavefront (um) at pupil point (rho, theta) for aberrations oriented along field azimuth phi.
pub fn wavefront(a: &FieldAberrations, rho: f64, theta: f64, phi: f64) -> f64 {
    let r2 = rho * rho;
    let t = theta - phi;
    a.defocus * 3f64.sqrt() * (2.0 * r2 - 1.0)
        + a.spherical * 5f64.sqrt() * (6.0 * r2 * r2 - 6.0 * r2 + 1.0)
        + a.coma * 8f64.sqrt() * (3.0 * r2 * rho - 2.0 * rho) * t.cos()
        + a.astigmatism * 6f64.sqrt() * r2 * (2.0 * t).cos()
}

/// One wavelength's PSF on an oversampled grid: (intensity [m][m], m, sample spacing um).
pub fn psf_oversampled(lens: &Lens, lambda_um: f64, a: &FieldAberrations, phi: f64) -> (Vec<f32>, usize, f64) {
    let target_dx = lens.pixel_um / OVERSAMPLE as f64;
    let p = PUPIL_SAMPLES;
    let m = ((lambda_um * lens.f_number * p as f64 / target_dx).round() as usize).max(2 * p);
    let dx = lambda_um * lens.f_number * p as f64 / m as f64;
    let mut field = vec![Complex32::default(); m * m];
    let c = (p as f64 - 1.0) / 2.0;
    for y in 0..p {
        for x in 0..p {
            let (u, v) = ((x as f64 - c) / (p as f64 / 2.0), (y as f64 - c) / (p as f64 / 2.0));
            let rho = (u * u + v * v).sqrt();
            if rho <= 1.0 {
                let phase = std::f64::consts::TAU * wavefront(a, rho, v.atan2(u), phi) / lambda_um;
                field[y * m + x] = Complex32::from_polar(1.0, phase as f32);
            }
        }
    }
    let psf = power_spectrum_centred(&mut field, &Fft2::new(m, m));
    let s: f64 = psf.iter().map(|&v| v as f64).sum();
    (psf.iter().map(|&v| (v as f64 / s) as f32).collect(), m, dx)
}

/// Band-averaged PSF binned to a `k x k` detector-pixel kernel centred on the paraxial image
/// point; sums to 1.
pub fn psf_kernel(lens: &Lens, a: &FieldAberrations, phi: f64, k: usize) -> Vec<f32> {
    let mut kernel = vec![0f64; k * k];
    let half = (k / 2) as i64;
    for &lambda in &lens.wavelengths_um {
        let (psf, m, dx) = psf_oversampled(lens, lambda, a, phi);
        let c = (m / 2) as f64;
        for y in 0..m {
            let py = (((y as f64 - c) * dx) / lens.pixel_um).round() as i64 + half;
            if py < 0 || py >= k as i64 {
                continue;
            }
            for x in 0..m {
                let px = (((x as f64 - c) * dx) / lens.pixel_um).round() as i64 + half;
                if px >= 0 && px < k as i64 {
                    kernel[py as usize * k + px as usize] += psf[y * m + x] as f64;
                }
            }
        }
    }
    let s: f64 = kernel.iter().sum();
    kernel.iter().map(|&v| (v / s) as f32).collect()
}

#[derive(Debug, Clone, Serialize)]
pub struct RegionPsf {
    pub row: usize,
    pub col: usize,
    /// Normalized field height (0 on axis, 1 at the corner) and azimuth (rad) of the region centre.
    pub field_height: f64,
    pub azimuth: f64,
    pub aberrations: FieldAberrations,
}

/// One kernel per region of a rows x cols grid over the sensor: (regions, kernels).
pub fn simulate(lens: &Lens, rows: usize, cols: usize, k: usize) -> (Vec<RegionPsf>, Vec<Vec<f32>>) {
    let [w, h] = lens.sensor;
    let r_max = ((w as f64 / 2.0).powi(2) + (h as f64 / 2.0).powi(2)).sqrt();
    let regions: Vec<RegionPsf> = (0..rows * cols)
        .map(|i| {
            let (row, col) = (i / cols, i % cols);
            let x = (col as f64 + 0.5) * w as f64 / cols as f64 - w as f64 / 2.0;
            let y = (row as f64 + 0.5) * h as f64 / rows as f64 - h as f64 / 2.0;
            let field_height = (x * x + y * y).sqrt() / r_max;
            RegionPsf { row, col, field_height, azimuth: y.atan2(x), aberrations: lens.at_field(field_height) }
        })
        .collect();
    let kernels = regions.par_iter().map(|r| psf_kernel(lens, &r.aberrations, r.azimuth, k)).collect();
    (regions, kernels)
}
