//! A simulated (or calibrated) PSF set on disk:
//! `psfs.npy` float32 [rows * cols, k, k] (each kernel sums to 1, row-major regions),
//! `psf.yaml` (grid, kernel size, lens, per-region field position, aberrations and spot
//! statistics) and `montage.png` (kernels side by side, each scaled to its peak, gamma 0.5).

use super::blur_index::{spot_stats, SpotStats};
use super::lens::{FieldAberrations, Lens};
use super::npy;
use super::psf::RegionPsf;
use crate::fsutil::{ensure_dir, write_atomic};
use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

pub struct PsfSet {
    pub rows: usize,
    pub cols: usize,
    pub k: usize,
    pub kernels: Vec<Vec<f32>>,
}

#[derive(Serialize, Deserialize)]
struct Description {
    lens: String,
    grid: [usize; 2],
    kernel_size: usize,
    pixel_um: f64,
    sensor: [usize; 2],
    wavelengths_um: Vec<f64>,
    regions: Vec<RegionEntry>,
}

#[derive(Serialize, Deserialize)]
struct RegionEntry {
    row: usize,
    col: usize,
    field_height: f64,
    azimuth_rad: f64,
    zernike_um: [f64; 4],
    centroid_px: [f64; 2],
    rms_radius_px: f64,
}

impl PsfSet {
    pub fn stats(&self) -> Vec<SpotStats> {
        self.kernels.iter().map(|k| spot_stats(k, self.k)).collect()
    }

    pub fn save(&self, dir: &Path, lens: &Lens, regions: &[RegionPsf]) -> Result<()> {
        ensure_dir(dir)?;
        let flat: Vec<f32> = self.kernels.concat();
        write_atomic(&dir.join("psfs.npy"), &npy::to_bytes(&[self.kernels.len(), self.k, self.k], &flat))?;
        let stats = self.stats();
        let zern = |a: &FieldAberrations| [a.defocus, a.spherical, a.coma, a.astigmatism];
        let d = Description {
            lens: lens.name.clone(),
            grid: [self.rows, self.cols],
            kernel_size: self.k,
            pixel_um: lens.pixel_um,
            sensor: lens.sensor,
            wavelengths_um: lens.wavelengths_um.clone(),
            regions: regions
                .iter()
                .zip(&stats)
                .map(|(r, s)| RegionEntry { row: r.row, col: r.col, field_height: r.field_height, azimuth_rad: r.azimuth, zernike_um: zern(&r.aberrations), centroid_px: s.centroid, rms_radius_px: s.rms_radius })
                .collect(),
        };
        let header = "# PSF set written by `pdi-compile psf simulate`. zernike_um: defocus, spherical, coma, astigmatism (um RMS).\n";
        write_atomic(&dir.join("psf.yaml"), format!("{header}{}", yaml_serde::to_string(&d)?).as_bytes())?;
        write_atomic(&dir.join("montage.png"), &self.montage_png()?)
    }

    pub fn load(dir: &Path) -> Result<PsfSet> {
        let text = std::fs::read_to_string(dir.join("psf.yaml")).with_context(|| format!("{} is not a PSF set (no psf.yaml); make one with `pdi-compile psf simulate`", dir.display()))?;
        let d: Description = yaml_serde::from_str(&text).map_err(|e| anyhow!("{}/psf.yaml: {e}", dir.display()))?;
        let a = npy::read(&dir.join("psfs.npy"))?;
        let [rows, cols] = d.grid;
        let k = d.kernel_size;
        if a.shape != [rows * cols, k, k] {
            bail!("{}/psfs.npy has shape {:?}; psf.yaml says {} kernels of {k}x{k}", dir.display(), a.shape, rows * cols);
        }
        if k.is_multiple_of(2) {
            bail!("kernel size {k} must be odd (kernels centre on a pixel)");
        }
        let kernels: Vec<Vec<f32>> = a.data.chunks_exact(k * k).map(|c| c.to_vec()).collect();
        for (i, kern) in kernels.iter().enumerate() {
            let s: f64 = kern.iter().map(|&v| v as f64).sum();
            if (s - 1.0).abs() > 1e-3 || kern.iter().any(|v| !v.is_finite() || *v < 0.0) {
                bail!("{}/psfs.npy: kernel {i} sums to {s} or holds negative/non-finite values; PSFs must be normalized", dir.display());
            }
        }
        Ok(PsfSet { rows, cols, k, kernels })
    }

    fn montage_png(&self) -> Result<Vec<u8>> {
        let gap = 2;
        let (w, h) = (self.cols * (self.k + gap) + gap, self.rows * (self.k + gap) + gap);
        let mut img = image::GrayImage::new(w as u32, h as u32);
        for (i, kern) in self.kernels.iter().enumerate() {
            let (r, c) = (i / self.cols, i % self.cols);
            let peak = kern.iter().cloned().fold(f32::MIN, f32::max).max(1e-12);
            for y in 0..self.k {
                for x in 0..self.k {
                    let v = (kern[y * self.k + x] / peak).max(0.0).sqrt();
                    img.put_pixel((gap + c * (self.k + gap) + x) as u32, (gap + r * (self.k + gap) + y) as u32, image::Luma([(v * 255.0) as u8]));
                }
            }
        }
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png).map_err(|e| anyhow!("cannot encode montage: {e}"))?;
        Ok(out.into_inner())
    }
}
