//! Input frames for verification and calibration: image folders (8/16-bit grayscale PNG or
//! TIFF, float `.npy`) with optional YOLO labels, or deterministic synthetic thermal frames.

use crate::metrics::coco_map::Truth;
use crate::optics::npy;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Context, Result};
use std::path::{Path, PathBuf};

#[derive(Clone)]
pub struct Frame {
    pub name: String,
    /// [1, 1, H, W], values in [0, 1].
    pub image: Tensor,
    /// Boxes from a YOLO label file beside the image, in pixels.
    pub labels: Option<Vec<Truth>>,
}

/// Frames from `dir`, each `height x width` (the model's input size). Frames of another
/// size are area-resized and colour frames converted to luma, each with one warning on
/// stderr saying how many: a deployment's frames rarely match the model exactly, and
/// refusing them would push users to resize by hand with worse filters.
pub fn load_folder(dir: &Path, height: usize, width: usize) -> Result<Vec<Frame>> {
    let (mut resized, mut colour) = (Vec::new(), 0usize);
    let mut frames = Vec::new();
    for f in crate::frames::image_files(dir)? {
        let g = decode(&f).with_context(|| format!("{}", f.display()))?;
        colour += usize::from(g.channels > 1);
        let data = if (g.w, g.h) == (width, height) {
            g.data
        } else {
            resized.push((g.w, g.h));
            crate::frames::resize_area(&g.data, g.w, g.h, width, height)
        };
        let labels = read_yolo_labels(&f.with_extension("txt"), width as f32, height as f32)?;
        frames.push(Frame { name: f.file_name().unwrap_or_default().to_string_lossy().into_owned(), image: Tensor::f32(vec![1, 1, height, width], data), labels });
    }
    if let Some(&(w, h)) = resized.first() {
        crate::warn::warn(format!("{}: {} frame(s) are not {width}x{height} (the first is {w}x{h}); area-resized to the model's input, labels kept normalized", dir.display(), resized.len()));
    }
    if colour > 0 {
        crate::warn::warn(format!("{}: {colour} frame(s) have colour channels; converted to luma (thermal frames are single-channel)", dir.display()));
    }
    Ok(frames)
}

/// How many frames `dir` holds (image files by name; none are decoded): what a recipe check
/// can afford before any pass runs.
pub fn count(dir: &Path) -> Result<usize> {
    if !dir.is_dir() {
        bail!("no such folder");
    }
    Ok(crate::frames::image_files(dir)?.len())
}

/// A frame as stored, before any resizing: luma values in [0, 1].
pub struct Gray {
    pub w: usize,
    pub h: usize,
    pub data: Vec<f32>,
    /// Channels of the stored image (1 for luma and .npy).
    pub channels: usize,
    /// Bits per sample: 8 or 16 for integer images (scaled by their full scale), 32 for float
    /// samples (.npy taken as is; a float image has no full scale to scale by).
    pub bits: u8,
}

/// A grayscale frame as (width, height, values in [0, 1]): 8/16-bit PNG or TIFF (by full
/// scale of the bit depth; colour images converted to luma), or a float `.npy` [H, W] taken as is.
pub fn read_gray(path: &Path) -> Result<(usize, usize, Vec<f32>)> {
    decode(path).map(|g| (g.w, g.h, g.data))
}

/// A frame file as stored (see [`Gray`]).
pub fn decode(path: &Path) -> Result<Gray> {
    if path.extension().is_some_and(|e| e == "npy") {
        let a = npy::read(path)?;
        let dims: Vec<usize> = a.shape.iter().copied().filter(|&d| d != 1).collect();
        let [h, w] = dims[..] else { bail!("expected a [H, W] array, got {:?}", a.shape) };
        return Ok(Gray { w, h, data: a.data, channels: 1, bits: 32 });
    }
    let bytes = std::fs::read(path).map_err(|e| anyhow!("cannot read: {e}"))?;
    decode_image(&bytes)
}

/// Largest frame side accepted: 16k pixels (a 16384 x 16384 f32 frame is 1 GiB already).
const MAX_SIDE: u32 = 16384;
/// Largest allocation the decoder may make for one frame.
const MAX_DECODE_BYTES: u64 = 1 << 30;

/// A PNG or TIFF frame from memory as (width, height, values in [0, 1]); the format is read
/// from the bytes, and the decoder's allocations are bounded (frames are untrusted input).
pub fn decode_bytes(bytes: &[u8]) -> Result<(usize, usize, Vec<f32>)> {
    decode_image(bytes).map(|g| (g.w, g.h, g.data))
}

fn decode_image(bytes: &[u8]) -> Result<Gray> {
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes)).with_guessed_format().map_err(|e| anyhow!("cannot read image: {e}"))?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_SIDE);
    limits.max_image_height = Some(MAX_SIDE);
    limits.max_alloc = Some(MAX_DECODE_BYTES);
    reader.limits(limits);
    let img = reader.decode().map_err(|e| anyhow!("cannot decode image: {e}"))?;
    let (w, h) = (img.width() as usize, img.height() as usize);
    let channels = img.color().channel_count() as usize - usize::from(img.color().has_alpha());
    let bits = (img.color().bits_per_pixel() / u16::from(img.color().channel_count())) as u8;
    let data: Vec<f32> = match img {
        image::DynamicImage::ImageLuma8(b) => b.into_raw().iter().map(|&v| v as f32 / 255.0).collect(),
        image::DynamicImage::ImageLuma16(b) => b.into_raw().iter().map(|&v| v as f32 / 65535.0).collect(),
        other => other.to_luma32f().into_raw(),
    };
    Ok(Gray { w, h, data, channels, bits })
}

/// Writes values in [0, 1] as a 16-bit grayscale PNG, atomically.
pub fn write_gray16(path: &Path, w: usize, h: usize, data: &[f32]) -> Result<()> {
    let px: Vec<u16> = data.iter().map(|&v| (v.clamp(0.0, 1.0) * 65535.0).round() as u16).collect();
    let img = image::ImageBuffer::<image::Luma<u16>, _>::from_raw(w as u32, h as u32, px).ok_or_else(|| anyhow!("bad image size"))?;
    let mut out = std::io::Cursor::new(Vec::new());
    img.write_to(&mut out, image::ImageFormat::Png).map_err(|e| anyhow!("cannot encode {}: {e}", path.display()))?;
    crate::fsutil::write_atomic(path, &out.into_inner())
}

/// `class cx cy w h` per line, normalized to [0, 1]; None when the file does not exist.
pub fn read_yolo_labels(path: &Path, width: f32, height: f32) -> Result<Option<Vec<Truth>>> {
    let Ok(text) = std::fs::read_to_string(path) else { return Ok(None) };
    let mut out = Vec::new();
    for (i, line) in text.lines().enumerate().filter(|(_, l)| !l.trim().is_empty()) {
        let v: Vec<f32> = line.split_whitespace().map(|s| s.parse::<f32>()).collect::<std::result::Result<_, _>>().map_err(|_| anyhow!("{}:{}: not numbers", path.display(), i + 1))?;
        let [c, cx, cy, w, h] = v[..] else { bail!("{}:{}: expected `class cx cy w h`", path.display(), i + 1) };
        out.push(Truth { class: c as usize, bbox: [(cx - w / 2.0) * width, (cy - h / 2.0) * height, (cx + w / 2.0) * width, (cy + h / 2.0) * height] });
    }
    Ok(Some(out))
}

/// `n` synthetic frames: sky/ground gradient, low-frequency texture, warm blobs, noise.
/// Deterministic in `seed`; a stand-in where no camera frames are given.
pub fn synthetic(n: usize, height: usize, width: usize, seed: u64) -> Vec<Frame> {
    let mut state = seed.wrapping_mul(0x9E3779B97F4A7C15).wrapping_add(1);
    let mut rnd = move || {
        state = state.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((state >> 40) as f32) / ((1u64 << 24) as f32)
    };
    (0..n)
        .map(|k| {
            let horizon = (0.3 + 0.3 * rnd()) * height as f32;
            let (fx, fy, ph) = (1.0 + 5.0 * rnd(), 1.0 + 5.0 * rnd(), 6.0 * rnd());
            let blobs: Vec<[f32; 5]> = (0..2 + (rnd() * 7.0) as usize)
                .map(|_| [rnd() * width as f32, horizon + rnd() * (height as f32 - horizon), 3.0 + rnd() * width as f32 / 10.0, 3.0 + rnd() * height as f32 / 8.0, 0.2 + 0.3 * rnd()])
                .collect();
            let mut data = Vec::with_capacity(height * width);
            for y in 0..height {
                for x in 0..width {
                    let (xf, yf) = (x as f32, y as f32);
                    let mut v = if yf < horizon { 0.15 + 0.05 * yf / height as f32 } else { 0.35 + 0.15 * (yf - horizon) / height as f32 };
                    v += 0.03 * (std::f32::consts::TAU * fx * xf / width as f32 + ph).sin() * (std::f32::consts::TAU * fy * yf / height as f32).cos();
                    for b in &blobs {
                        let d = ((xf - b[0]) / b[2]).powi(2) + ((yf - b[1]) / b[3]).powi(2);
                        v += b[4] * (-d * d).exp();
                    }
                    v += 0.02 * (rnd() - 0.5);
                    data.push(v.clamp(0.0, 1.0));
                }
            }
            Frame { name: format!("synthetic_{k}"), image: Tensor::f32(vec![1, 1, height, width], data), labels: None }
        })
        .collect()
}

/// A window of a frame, in pixels: what a scene's `roi` keeps, and what a cropped model sees
/// of its teacher's frame.
#[derive(Clone, Copy, Debug, serde::Deserialize, serde::Serialize, PartialEq, Eq)]
#[serde(deny_unknown_fields)]
pub struct Roi {
    pub x: usize,
    pub y: usize,
    pub w: usize,
    pub h: usize,
}

impl Roi {
    /// Whether a box (x1, y1, x2, y2) lies inside, at least `margin` pixels from every edge.
    pub fn contains(&self, b: &[f32; 4], margin: f32) -> bool {
        let (x0, y0) = (self.x as f32 + margin, self.y as f32 + margin);
        let (x1, y1) = ((self.x + self.w) as f32 - margin, (self.y + self.h) as f32 - margin);
        b[0] >= x0 && b[1] >= y0 && b[2] <= x1 && b[3] <= y1
    }

    /// The ROI of a [.., H, W] image (None when the image does not hold it).
    pub fn crop(&self, t: &crate::tensor::Tensor) -> Option<crate::tensor::Tensor> {
        let n = t.shape.len();
        if n < 2 {
            return None;
        }
        let rows: Vec<usize> = (self.y..self.y + self.h).collect();
        let cols: Vec<usize> = (self.x..self.x + self.w).collect();
        t.select(n - 2, &rows).and_then(|c| c.select(n - 1, &cols))
    }
}

/// The image files of a folder (PNG, TIFF, .npy), sorted; an error when there are none.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("cannot read {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| matches!(p.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref(), Some("png" | "tif" | "tiff" | "npy")))
        .collect();
    v.sort();
    if v.is_empty() {
        bail!("{} holds no .png, .tif or .npy images", dir.display());
    }
    Ok(v)
}

/// Area-average resampling (exact box integration), row-major.
pub fn resize_area(src: &[f32], sw: usize, sh: usize, dw: usize, dh: usize) -> Vec<f32> {
    let weights = |s: usize, d: usize| -> Vec<Vec<(usize, f32)>> {
        let scale = s as f64 / d as f64;
        (0..d)
            .map(|o| {
                let (a, b) = (o as f64 * scale, (o + 1) as f64 * scale);
                (a.floor() as usize..(b.ceil() as usize).min(s))
                    .map(|i| (i, ((b.min(i as f64 + 1.0) - a.max(i as f64)) / scale) as f32))
                    .filter(|&(_, w)| w > 0.0)
                    .collect()
            })
            .collect()
    };
    let (wx, wy) = (weights(sw, dw), weights(sh, dh));
    let mut rows = vec![0f32; sh * dw];
    for y in 0..sh {
        for (x, ws) in wx.iter().enumerate() {
            rows[y * dw + x] = ws.iter().map(|&(i, w)| src[y * sw + i] * w).sum();
        }
    }
    let mut out = vec![0f32; dh * dw];
    for (y, ws) in wy.iter().enumerate() {
        for x in 0..dw {
            out[y * dw + x] = ws.iter().map(|&(i, w)| rows[i * dw + x] * w).sum();
        }
    }
    out
}
