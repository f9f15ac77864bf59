//! The PSF-aware blur-index map: blur factors on a coarse field grid (6x8 by default),
//! normalized to [0, 1]. Read from `.npy` (float32 [rows, cols] or [1, 1, rows, cols]) or
//! YAML (`grid: [rows, cols]`, `values:` row-major).

use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;

#[derive(Clone, Debug, PartialEq)]
pub struct BlurMap {
    pub rows: usize,
    pub cols: usize,
    /// Row-major, each in [0, 1].
    pub values: Vec<f32>,
}

#[derive(serde::Deserialize)]
struct YamlBlurMap {
    grid: [usize; 2],
    values: Vec<f32>,
}

impl BlurMap {
    pub fn load(path: &Path) -> Result<BlurMap> {
        let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
        let map = match ext {
            "npy" => {
                let a = super::npy::read(path)?;
                let dims: Vec<usize> = a.shape.iter().copied().filter(|&d| d != 1).collect();
                match (a.shape.len(), dims.as_slice()) {
                    (2 | 4, [r, c]) => BlurMap { rows: *r, cols: *c, values: a.data },
                    _ => bail!("{}: blur map must be [rows, cols] or [1, 1, rows, cols], got {:?}", path.display(), a.shape),
                }
            }
            "yaml" | "yml" => {
                let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
                let y: YamlBlurMap = yaml_serde::from_str(&text).map_err(|e| anyhow!("{}: not a blur map ({e})", path.display()))?;
                BlurMap { rows: y.grid[0], cols: y.grid[1], values: y.values }
            }
            _ => bail!("{}: blur maps are .npy or .yaml files", path.display()),
        };
        map.validate().with_context(|| format!("{}", path.display()))?;
        Ok(map)
    }

    pub fn validate(&self) -> Result<()> {
        if self.rows * self.cols != self.values.len() || self.rows < 1 || self.cols < 1 {
            bail!("grid {}x{} needs {} values, file has {}", self.rows, self.cols, self.rows * self.cols, self.values.len());
        }
        if let Some(v) = self.values.iter().find(|v| !(0.0..=1.0).contains(*v)) {
            bail!("blur factor {v} lies outside [0, 1]; blur maps are normalized");
        }
        Ok(())
    }

    /// Uniform map: what a near diffraction-limited multi-lens camera gives.
    pub fn uniform(rows: usize, cols: usize, value: f32) -> BlurMap {
        BlurMap { rows, cols, values: vec![value; rows * cols] }
    }

    pub fn to_yaml(&self) -> String {
        let vals: Vec<String> = self.values.iter().map(|v| format!("{v}")).collect();
        format!("grid: [{}, {}]\nvalues: [{}]\n", self.rows, self.cols, vals.join(", "))
    }
}
