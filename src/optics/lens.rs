//! Lens description files (YAML): aperture, detector, wavelengths and field-dependent
//! aberrations as Zernike coefficients.
//!
//! Each aberration is a polynomial in the normalized field height h (0 on axis, 1 at the
//! sensor corner): `[c0, c1, c2, ...]` gives c0 + c1 h + c2 h^2 + ... micrometres of RMS
//! wavefront (Noll-normalized Zernike terms). Defocus growing with h^2 is field curvature.

use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Lens {
    pub name: String,
    #[serde(default)]
    pub description: String,
    pub f_number: f64,
    pub focal_length_mm: f64,
    pub pixel_um: f64,
    /// Detector size in pixels, [width, height].
    pub sensor: [usize; 2],
    /// At least 5 across the band (LWIR: 8-12 um).
    pub wavelengths_um: Vec<f64>,
    pub aberrations: Aberrations,
}

#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Aberrations {
    pub defocus: Vec<f64>,
    pub spherical: Vec<f64>,
    pub coma: Vec<f64>,
    pub astigmatism: Vec<f64>,
}

/// Zernike coefficients (um RMS) at one field point.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct FieldAberrations {
    pub defocus: f64,
    pub spherical: f64,
    pub coma: f64,
    pub astigmatism: f64,
}

fn poly(c: &[f64], h: f64) -> f64 {
    c.iter().rev().fold(0.0, |acc, &k| acc * h + k)
}

impl Lens {
    pub fn load(path: &Path) -> Result<Lens> {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read lens file {}", path.display()))?;
        let lens: Lens = yaml_serde::from_str(&text).map_err(|e| anyhow!("lens file {}: {e}", path.display()))?;
        lens.validate().with_context(|| format!("lens file {}", path.display()))?;
        Ok(lens)
    }

    pub fn validate(&self) -> Result<()> {
        if !(0.5..=32.0).contains(&self.f_number) {
            bail!("f_number {} is outside 0.5-32", self.f_number);
        }
        if self.pixel_um <= 0.0 || self.focal_length_mm <= 0.0 {
            bail!("pixel_um and focal_length_mm must be positive");
        }
        if self.wavelengths_um.len() < 5 || self.wavelengths_um.iter().any(|&l| !(0.3..=20.0).contains(&l)) {
            bail!("give at least 5 wavelengths in micrometres (LWIR: 8-12)");
        }
        if self.sensor.iter().any(|&d| d == 0 || d > 16384) {
            bail!("sensor size {:?} is not a detector", self.sensor);
        }
        Ok(())
    }

    pub fn at_field(&self, h: f64) -> FieldAberrations {
        let a = &self.aberrations;
        FieldAberrations { defocus: poly(&a.defocus, h), spherical: poly(&a.spherical, h), coma: poly(&a.coma, h), astigmatism: poly(&a.astigmatism, h) }
    }
}
