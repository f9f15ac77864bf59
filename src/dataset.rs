//! Image sets on disk: synthetic scenes, degraded copies, calibration sets; real folders
//! with YOLO or COCO labels, rescaled with their boxes.

use crate::frames::{image_files, read_gray, read_yolo_labels, resize_area, write_gray16};
use crate::fsutil::{ensure_dir, write_atomic};
use crate::metrics::coco_map::Truth;
use crate::optics::degrade::{add_noise, psnr, NoiseModel, SpatialBlur};
use crate::optics::psf_set::PsfSet;
use crate::optics::rng::Rng;
use crate::optics::synth::{self, yolo_text, CLASSES};
use anyhow::{anyhow, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

fn progress(n: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(n as u64);
    pb.set_style(ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} {per_sec} eta {eta}").expect("valid template").progress_chars("=> "));
    pb.set_message(what.to_string());
    pb
}

/// Writes `n` synthetic scenes (`000000.png` 16-bit + `000000.txt` YOLO labels) to `out`.
/// Boxes with a side under `min_box` pixels are left unlabelled (for training sets that will
/// be downscaled: a 4-pixel target is noise at 256x192).
pub fn write_synthetic(out: &Path, n: usize, width: usize, height: usize, seed: u64, min_box: f32) -> Result<usize> {
    ensure_dir(out)?;
    write_atomic(&out.join("classes.txt"), (CLASSES.join("\n") + "\n").as_bytes())?;
    let pb = progress(n, "synth");
    let boxes = Mutex::new(0usize);
    (0..n).into_par_iter().try_for_each(|i| -> Result<()> {
        let mut s = synth::scene(width, height, seed.wrapping_mul(1_000_003).wrapping_add(i as u64));
        s.labels.retain(|t| t.bbox[2] - t.bbox[0] >= min_box && t.bbox[3] - t.bbox[1] >= min_box);
        write_gray16(&out.join(format!("{i:06}.png")), width, height, &s.pixels)?;
        write_atomic(&out.join(format!("{i:06}.txt")), yolo_text(&s.labels, width, height).as_bytes())?;
        *boxes.lock().expect("no poisoning") += s.labels.len();
        pb.inc(1);
        Ok(())
    })?;
    pb.finish_and_clear();
    Ok(boxes.into_inner().expect("no poisoning"))
}

#[derive(Serialize, Default)]
pub struct DegradeSummary {
    pub frames: usize,
    pub q: f64,
    pub sigma: f64,
    pub full_scale: f64,
    /// PSNR of the degraded frames against the clean ones, dB (mean over frames).
    pub psnr_db: f64,
    /// PSNR of the blur alone (before noise), dB.
    pub blur_psnr_db: f64,
}

/// Degrades every image of `input` (a file or a folder) into `output`, copying label files.
pub fn degrade_path(input: &Path, output: &Path, psf: &PsfSet, noise: NoiseModel, seed: u64) -> Result<DegradeSummary> {
    let files = if input.is_dir() { image_files(input)? } else { vec![input.to_path_buf()] };
    let out_for = |f: &Path| -> PathBuf {
        if input.is_dir() { output.join(f.file_name().expect("a file")).with_extension("png") } else { output.to_path_buf() }
    };
    if input.is_dir() {
        ensure_dir(output)?;
    }
    let blurs: Mutex<HashMap<(usize, usize), std::sync::Arc<SpatialBlur>>> = Mutex::new(HashMap::new());
    let pb = progress(files.len(), "degrade");
    let results: Vec<(f64, f64)> = files
        .par_iter()
        .enumerate()
        .map(|(i, f)| -> Result<(f64, f64)> {
            let (w, h, clean) = read_gray(f).with_context(|| format!("{}", f.display()))?;
            let blur = {
                let mut cache = blurs.lock().expect("no poisoning");
                cache.entry((h, w)).or_insert_with(|| std::sync::Arc::new(SpatialBlur::new(&psf.kernels, psf.k, psf.rows, psf.cols, h, w))).clone()
            };
            let blurred = blur.apply(&clean);
            let mut raw = blurred.clone();
            add_noise(&mut raw, &noise, &mut Rng::new(seed.wrapping_add(i as u64)));
            write_gray16(&out_for(f), w, h, &raw)?;
            let label = f.with_extension("txt");
            if input.is_dir() && label.exists() {
                std::fs::copy(&label, out_for(f).with_extension("txt"))?;
            }
            pb.inc(1);
            Ok((psnr(&clean, &raw), psnr(&clean, &blurred)))
        })
        .collect::<Result<_>>()?;
    pb.finish_and_clear();
    let n = results.len().max(1) as f64;
    Ok(DegradeSummary {
        frames: results.len(),
        q: noise.q,
        sigma: noise.sigma,
        full_scale: noise.full_scale,
        psnr_db: results.iter().map(|r| r.0).sum::<f64>() / n,
        blur_psnr_db: results.iter().map(|r| r.1.min(99.0)).sum::<f64>() / n,
    })
}


/// M3FD class index of a dataset's category name (FLIR ADAS and COCO spellings included).
pub fn m3fd_class(name: &str) -> Option<usize> {
    match name.to_ascii_lowercase().as_str() {
        "people" | "person" | "pedestrian" => Some(0),
        "car" => Some(1),
        "bus" => Some(2),
        "motorcycle" | "motor" | "motorbike" | "bike" | "bicycle" => Some(3),
        "lamp" | "light" | "street light" | "streetlight" | "traffic light" => Some(4),
        "truck" => Some(5),
        _ => None,
    }
}

/// COCO JSON boxes by image file name, mapped to M3FD classes (other categories dropped).
pub fn read_coco(path: &Path) -> Result<HashMap<String, Vec<Truth>>> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let j: serde_json::Value = serde_json::from_str(&text).map_err(|e| anyhow!("{}: not JSON ({e})", path.display()))?;
    let cats: HashMap<i64, Option<usize>> = j["categories"].as_array().into_iter().flatten().filter_map(|c| Some((c["id"].as_i64()?, m3fd_class(c["name"].as_str()?)))).collect();
    let files: HashMap<i64, String> = j["images"].as_array().into_iter().flatten().filter_map(|i| {
        let name = Path::new(i["file_name"].as_str()?).file_name()?.to_string_lossy().into_owned();
        Some((i["id"].as_i64()?, name))
    }).collect();
    let mut out: HashMap<String, Vec<Truth>> = files.values().map(|f| (f.clone(), Vec::new())).collect();
    for a in j["annotations"].as_array().into_iter().flatten() {
        let (Some(img), Some(cat), Some(b)) = (a["image_id"].as_i64(), a["category_id"].as_i64(), a["bbox"].as_array()) else { continue };
        let (Some(file), Some(Some(class))) = (files.get(&img), cats.get(&cat)) else { continue };
        let v: Vec<f32> = b.iter().filter_map(|x| x.as_f64().map(|x| x as f32)).collect();
        if v.len() == 4 {
            out.entry(file.clone()).or_default().push(Truth { class: *class, bbox: [v[0], v[1], v[0] + v[2], v[1] + v[3]] });
        }
    }
    Ok(out)
}


/// Copies a real folder to `out` at `width x height` (e.g. 1024x768 -> 640x480), boxes scaled
/// with the image; labels from YOLO txt beside each image or a COCO JSON (`coco`).
pub fn import_folder(input: &Path, out: &Path, width: usize, height: usize, coco: Option<&Path>) -> Result<usize> {
    let files = image_files(input)?;
    let coco = coco.map(read_coco).transpose()?;
    ensure_dir(out)?;
    let pb = progress(files.len(), "import");
    let boxes = Mutex::new(0usize);
    files.par_iter().enumerate().try_for_each(|(i, f)| -> Result<()> {
        let (w, h, px) = read_gray(f).with_context(|| format!("{}", f.display()))?;
        let labels = match &coco {
            Some(c) => c.get(&f.file_name().unwrap_or_default().to_string_lossy().into_owned()).cloned().unwrap_or_default(),
            None => read_yolo_labels(&f.with_extension("txt"), w as f32, h as f32)?.unwrap_or_default(),
        };
        let (sx, sy) = (width as f32 / w as f32, height as f32 / h as f32);
        let scaled: Vec<Truth> = labels.iter().map(|t| Truth { class: t.class, bbox: [t.bbox[0] * sx, t.bbox[1] * sy, t.bbox[2] * sx, t.bbox[3] * sy] }).collect();
        let img = if (w, h) == (width, height) { px } else { resize_area(&px, w, h, width, height) };
        write_gray16(&out.join(format!("{i:06}.png")), width, height, &img)?;
        write_atomic(&out.join(format!("{i:06}.txt")), yolo_text(&scaled, width, height).as_bytes())?;
        *boxes.lock().expect("no poisoning") += scaled.len();
        pb.inc(1);
        Ok(())
    })?;
    pb.finish_and_clear();
    Ok(boxes.into_inner().expect("no poisoning"))
}

/// Area-downscales every PNG of `dir` in place to `width x height` (YOLO labels are
/// normalized and stay valid). Frames are simulated at sensor size so PSFs keep their
/// physical pixel scale; training at a smaller size resamples afterwards, like a camera
/// pipeline that bins its output.
pub fn resize_folder(dir: &Path, width: usize, height: usize) -> Result<()> {
    image_files(dir)?.par_iter().try_for_each(|f| -> Result<()> {
        let (w, h, px) = read_gray(f)?;
        if (w, h) != (width, height) {
            write_gray16(f, width, height, &resize_area(&px, w, h, width, height))?;
        }
        Ok(())
    })
}
