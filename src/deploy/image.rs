//! Camera frames as `run` and the [`super::Detector`] take them: one file, a folder, or a
//! numbered sequence (`frames/%05d.png`), read whole and checked before any model runs.

use anyhow::{anyhow, bail, Context, Result};
use std::path::{Path, PathBuf};

/// A grayscale frame at its own size: luma in [0, 1] (integer images by their full scale),
/// row-major.
#[derive(Clone, Debug)]
pub struct Image {
    pub width: usize,
    pub height: usize,
    pub data: Vec<f32>,
    /// Bits per sample as stored: 8 or 16, or 32 for a float `.npy`.
    pub bits: u8,
}

impl Image {
    /// An 8/16-bit PNG or TIFF (colour converted to luma) or a float `.npy` [H, W]. A float
    /// image, an empty frame or non-finite values are refused: none of them has a meaning the
    /// model was trained on.
    pub fn read(path: impl AsRef<Path>) -> Result<Image> {
        let path = path.as_ref();
        let g = crate::frames::decode(path).with_context(|| path.display().to_string())?;
        let is_npy = path.extension().is_some_and(|e| e == "npy");
        if !is_npy && !matches!(g.bits, 8 | 16) {
            bail!("{}: {}-bit samples; frames are 8- or 16-bit images (scaled by their full scale) or .npy arrays in [0, 1]", path.display(), g.bits);
        }
        if g.w == 0 || g.h == 0 {
            bail!("{}: an empty frame ({}x{})", path.display(), g.w, g.h);
        }
        if let Some(i) = g.data.iter().position(|v| !v.is_finite()) {
            bail!("{}: value {} at pixel ({}, {}) is not finite", path.display(), g.data[i], i % g.w, i / g.w);
        }
        Ok(Image { width: g.w, height: g.h, data: g.data, bits: g.bits })
    }
}

/// The frames `spec` names, in order: a file; a folder's frame files sorted by name; or a
/// numbered sequence `name%0Nd.ext` read from the first number that exists (0 or 1) until
/// the next is missing.
pub fn list(spec: &Path) -> Result<Vec<PathBuf>> {
    let text = spec.to_string_lossy();
    if let Some(at) = text.find('%') {
        return sequence(&text, at);
    }
    if spec.is_dir() {
        return crate::frames::image_files(spec);
    }
    if !spec.exists() {
        bail!("{}: no such frame, folder or sequence", spec.display());
    }
    Ok(vec![spec.to_path_buf()])
}

/// `name%05d.png`: the digits' width after `%0`, then `d`.
fn sequence(text: &str, at: usize) -> Result<Vec<PathBuf>> {
    let rest = &text[at + 1..];
    let end = rest.find('d').ok_or_else(|| anyhow!("{text}: a numbered sequence is written like frames/%05d.png"))?;
    let width: usize = if end == 0 { 0 } else { rest[..end].parse().map_err(|_| anyhow!("{text}: a numbered sequence is written like frames/%05d.png"))? };
    if width > 12 || rest[end + 1..].contains('%') {
        bail!("{text}: a numbered sequence is written like frames/%05d.png");
    }
    let name = |i: usize| PathBuf::from(format!("{}{:0width$}{}", &text[..at], i, &rest[end + 1..]));
    let first = if name(0).exists() { 0 } else { 1 };
    let v: Vec<PathBuf> = (first..).map(name).take_while(|p| p.is_file()).collect();
    if v.is_empty() {
        bail!("{text}: no frame of this sequence exists (looked for {} and {})", name(0).display(), name(1).display());
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sequences_run_until_the_first_gap() {
        let dir = tempfile::tempdir().unwrap();
        for i in [1, 2, 3, 5] {
            std::fs::write(dir.path().join(format!("f{i:03}.png")), b"x").unwrap();
        }
        let got = list(&dir.path().join("f%03d.png")).unwrap();
        let names: Vec<String> = got.iter().map(|p| p.file_name().unwrap().to_string_lossy().into_owned()).collect();
        assert_eq!(names, ["f001.png", "f002.png", "f003.png"]);
        assert!(list(&dir.path().join("g%03d.png")).is_err());
        assert!(list(&dir.path().join("f%3x.png")).is_err());
    }
}
