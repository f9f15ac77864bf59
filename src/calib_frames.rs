//! Calibration frames for data-driven passes (pruning compensation, INT8 ranges): a folder
//! of camera frames (`--calib`), or, when none is given, frames made by the physics
//! pipeline: synthetic thermal scenes through the single-lens PSF of
//! `calib/lens_single_lwir.yaml` plus detector noise, the degradation PDI-Net is trained on.

use crate::analysis::partition::image_input;
use crate::frames::{self, Frame};
use crate::ir::{Graph, Inferred};
use crate::optics::degrade::{add_noise, NoiseModel, SpatialBlur, FULL_SCALE_14BIT};
use crate::optics::lens::Lens;
use crate::optics::rng::Rng;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use std::path::Path;

/// The lens of the default calibration set, compiled in so the binary works anywhere.
const DEFAULT_LENS: &str = include_str!("../calib/lens_single_lwir.yaml");
/// Region grid and kernel size of the simulated PSFs (those of `psf simulate`'s defaults).
const PSF_GRID: (usize, usize) = (6, 8);
const PSF_KERNEL: usize = 31;
/// Noise of the default set: quantization step 90 counts of a 14-bit detector, sigma 2 steps
/// (`pdi-compile dataset`'s defaults, which made the trained model's training frames).
const NOISE: NoiseModel = NoiseModel { q: 90.0, sigma: 2.0, full_scale: FULL_SCALE_14BIT };

pub struct CalibrationSet {
    pub frames: Vec<Frame>,
    /// Where they came from, for reports.
    pub source: String,
}

/// Refuses a frame no calibration should read: non-finite pixels (they turn every range
/// they touch into NaN) or one value everywhere (no signal, and a zero variance downstream).
fn check_frame(f: &Frame) -> Result<()> {
    let v = f.image.as_f32().ok_or_else(|| anyhow!("frame is not float"))?;
    let bad = v.iter().filter(|x| !x.is_finite()).count();
    if bad > 0 {
        bail!("{bad} non-finite pixel(s); calibration frames must be finite: fix or remove the frame");
    }
    if let Some(&first) = v.first() {
        if v.iter().all(|&x| x == first) {
            bail!("every pixel is {first}: a constant frame carries nothing to calibrate on; remove it");
        }
    }
    Ok(())
}

/// Up to `n` frames of `height x width` from `folder` (sorted by name), or `n` simulated ones.
pub fn calibration_frames(folder: Option<&Path>, n: usize, height: usize, width: usize, seed: u64) -> Result<CalibrationSet> {
    calibration_frames_from(folder, 0, n, height, width, seed)
}

/// Frames `first..first + n` of the set `calibration_frames` draws (the same frames, without
/// making the first ones): a pass that wants more frames later continues its draw.
pub fn calibration_frames_from(folder: Option<&Path>, first: usize, n: usize, height: usize, width: usize, seed: u64) -> Result<CalibrationSet> {
    if n == 0 {
        bail!("a calibration set needs at least one frame");
    }
    if let Some(dir) = folder {
        let mut frames = frames::load_folder(dir, height, width)?;
        if frames.is_empty() {
            bail!("no frames in {} (PNG/TIFF 8/16-bit grayscale or .npy); point --calib at camera frames", dir.display());
        }
        let held = frames.len();
        frames.drain(..first.min(held));
        frames.truncate(n);
        for f in &frames {
            check_frame(f).map_err(|e| anyhow!("{}: {e}", dir.join(&f.name).display()))?;
        }
        if frames.len() < n {
            let asked = if first == 0 { format!("{n}") } else { format!("frames {} to {}", first + 1, first + n) };
            crate::warn::warn(format!("{} holds {held} frame(s); the pass asked for {asked}: its statistics rest on fewer frames", dir.display()));
        }
        let source = format!("{} frames from {}", frames.len(), dir.display());
        return Ok(CalibrationSet { frames, source });
    }
    let lens: Lens = yaml_serde::from_str(DEFAULT_LENS).map_err(|e| anyhow!("built-in lens: {e}"))?;
    let (_, kernels) = crate::optics::psf::simulate(&lens, PSF_GRID.0, PSF_GRID.1, PSF_KERNEL);
    // Degrade at the sensor's resolution (where the PSF is defined), then area-resize to the
    // model's input, as `pdi-compile dataset --out-size` makes training sets.
    let [sw, sh] = lens.sensor;
    let blur = SpatialBlur::new(&kernels, PSF_KERNEL, PSF_GRID.0, PSF_GRID.1, sh, sw);
    let pb = ProgressBar::new(n as u64);
    pb.set_style(ProgressStyle::with_template("calibration frames [{bar:30}] {pos}/{len}").expect("valid template").progress_chars("=> "));
    let frames = (first..first + n)
        .into_par_iter()
        .map(|i| {
            let s = crate::optics::synth::scene(sw, sh, seed.wrapping_mul(7919).wrapping_add(i as u64));
            let mut img = blur.apply(&s.pixels);
            add_noise(&mut img, &NOISE, &mut Rng::new(seed.wrapping_add(1_000 + i as u64)));
            let img = if (sw, sh) == (width, height) { img } else { crate::frames::resize_area(&img, sw, sh, width, height) };
            pb.inc(1);
            Frame { name: format!("physics_{i:04}"), image: Tensor::f32(vec![1, 1, height, width], img), labels: None }
        })
        .collect();
    pb.finish_and_clear();
    Ok(CalibrationSet { frames, source: format!("{n} physics-pipeline frames ({}, q {} sigma {}, seed {seed})", lens.name, NOISE.q, NOISE.sigma) })
}

/// Calibration feeds for a model: `n` frames fed to its single-channel image input (every
/// other input must already be bound, as `bind-psf` binds the blur map), and their source.
pub fn image_feeds(graph: &Graph, inf: &Inferred, folder: Option<&Path>, n: usize, seed: u64) -> Result<(Vec<Vec<(String, Tensor)>>, String)> {
    image_feeds_from(graph, inf, folder, 0, n, seed)
}

/// Feeds of frames `first..first + n` of `image_feeds`'s draw.
pub fn image_feeds_from(graph: &Graph, inf: &Inferred, folder: Option<&Path>, first: usize, n: usize, seed: u64) -> Result<(Vec<Vec<(String, Tensor)>>, String)> {
    let image = image_input(graph, inf).ok_or_else(|| anyhow!("calibration needs a [1, C, H, W] image input"))?;
    if let Some(other) = graph.inputs.iter().find(|v| v.name != image) {
        bail!("input '{}' has no calibration value; run bind-psf (with --psf) first", other.name);
    }
    let s = inf.shape(&image).ok_or_else(|| anyhow!("image input '{image}' has no static shape"))?;
    let channels = Some(s[1]).filter(|&c| (1..=16).contains(&c)).ok_or_else(|| anyhow!("image input '{image}' has {} channels; expected 1 to 16", s[1]))?;
    let set = calibration_frames_from(folder, first, n, s[2], s[3], seed)?;
    if channels > 1 {
        crate::warn::warn(format!("image input '{image}' takes {channels} channels; each single-channel calibration frame is replicated into all of them (thermal frames stored as RGB)"));
    }
    Ok((set.frames.into_iter().map(|f| vec![(image.clone(), replicate(&f.image, channels))]).collect(), set.source))
}

/// The most bytes of f32 pixels a training set may take. A training pass holds its frames in
/// this process, in the file handed to the torch worker and in the worker (three copies), so
/// 2 GiB keeps it well inside a 24 GiB machine: 8192 frames at 256x192 take 1.5 GiB; at
/// 640x480, 1747 fit.
const TRAINING_FRAME_BYTES: usize = 2 << 30;

/// `asked` training frames for `pass`, or as many as fit in TRAINING_FRAME_BYTES at the image
/// input's size (with a warning), never fewer than 64.
pub fn affordable_frames(pass: &str, graph: &Graph, inf: &Inferred, asked: usize) -> usize {
    let per_frame = image_input(graph, inf).and_then(|i| inf.shape(&i)).map_or(0, |s| s.iter().map(|&d| d.max(1)).product::<usize>() * 4);
    let fit = (TRAINING_FRAME_BYTES / per_frame.max(1)).max(64);
    if asked > fit {
        crate::warn::warn(format!("{pass}: {asked} training frames of {per_frame} bytes would take over {} GiB; training on {fit} (ask for at most {fit} to silence this)", TRAINING_FRAME_BYTES >> 30));
        return fit;
    }
    asked
}

/// A [1, 1, H, W] frame repeated into [1, C, H, W].
pub fn replicate(frame: &Tensor, channels: usize) -> Tensor {
    if channels == 1 {
        return frame.clone();
    }
    let plane = frame.as_f32().unwrap_or_default();
    let mut shape = frame.shape.clone();
    shape[1] = channels;
    Tensor::f32(shape, plane.repeat(channels))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Continuing a draw gives the frames the longer draw would have held, simulated or from a
    /// folder, so a pass can add frames later without repeating any.
    #[test]
    fn a_draw_continued_is_the_longer_draw() {
        let pixels = |set: &CalibrationSet| set.frames.iter().map(|f| f.image.as_f32().unwrap().to_vec()).collect::<Vec<_>>();
        let whole = calibration_frames(None, 5, 24, 32, 9).unwrap();
        let tail = calibration_frames_from(None, 3, 2, 24, 32, 9).unwrap();
        assert_eq!(pixels(&tail), pixels(&whole)[3..]);
        assert_ne!(pixels(&tail)[0], pixels(&whole)[0]);

        let dir = tempfile::tempdir().unwrap();
        for (i, f) in whole.frames.iter().enumerate() {
            std::fs::write(dir.path().join(format!("f{i}.npy")), crate::optics::npy::to_bytes(&[24, 32], f.image.as_f32().unwrap())).unwrap();
        }
        let folder = calibration_frames_from(Some(dir.path()), 3, 4, 24, 32, 9).unwrap();
        assert_eq!(pixels(&folder), pixels(&whole)[3..]);
    }
}
