//! `pdi-compile run ARTIFACT --frames PATH -o OUT`: what a shipped artifact detects on camera
//! frames, through [`crate::deploy::Detector`] (the path camera code embeds).
//!
//! Writes, as one folder that appears whole or not at all:
//!   OUT/detections.json   COCO results (image_id, category_id, bbox xywh, score) with each
//!                         frame's file and each class's name
//!   OUT/labels/*.txt      YOLO `class cx cy w h score`, normalized to the frame
//!   OUT/images/*.png      the frame with its boxes (side by side with `--compare`)
//!   OUT/contact_sheet.png the first frames' pictures in a grid
//!   OUT/run.json          settings, per-stage latency (median / p95 / p99), frames/s, and
//!                         mAP against YOLO labels found beside the frames
//! mAP is computed as `verify` computes it (decoded at conf 0.001, validation's NMS), so the two
//! agree on the same frames; the files hold the detections above `--conf`.

use crate::deploy::{draw, image, Detector, Image, Options, EVAL_CONF};
use crate::detect::Detection;
use crate::fsutil::{write_atomic, StagedDir};
use crate::metrics::coco_map::{coco_map, MapResult, Truth};
use anyhow::{Context, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Pictures on the contact sheet.
pub const SHEET_FRAMES: usize = 16;

pub struct RunRequest {
    pub artifact: PathBuf,
    pub frames: PathBuf,
    pub out: PathBuf,
    pub options: Options,
    /// Another artifact run on the same frames, as the reference the first is compared with.
    pub compare: Option<PathBuf>,
}

/// One stage's per-frame times in milliseconds.
#[derive(Serialize, Debug, Clone, Copy)]
pub struct StageTimes {
    pub median_ms: f64,
    pub p95_ms: f64,
    pub p99_ms: f64,
    /// Its share of the per-frame total (medians).
    pub share: f64,
}

#[derive(Serialize, Debug, Clone)]
pub struct Latency {
    pub load_ms: f64,
    pub preprocess: StageTimes,
    pub inference: StageTimes,
    pub decode_nms: StageTimes,
    /// Frames over the summed time of the three stages.
    pub frames_per_second: f64,
}

#[derive(Serialize, Debug, Clone)]
pub struct Side {
    pub artifact: String,
    pub model: String,
    pub engine: crate::runtime::Engine,
    pub why: String,
    pub threads: usize,
    pub detections: usize,
    pub latency: Latency,
    /// Against the YOLO labels beside the frames (frames without a label file hold no objects).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub map_labels: Option<MapResult>,
}

#[derive(Serialize, Debug, Clone)]
pub struct Comparison {
    pub other: Side,
    /// mAP@0.5:0.95 and @0.5 of this artifact's detections with the other's confident ones
    /// taken as truth (as `verify` scores a candidate against its reference).
    pub agreement: MapResult,
    pub truth: String,
    /// Detections above --conf that only one of the two made (same class, IoU ≥ 0.5).
    pub only_this: usize,
    pub only_other: usize,
}

#[derive(Serialize, Debug, Clone)]
pub struct RunReport {
    pub frames: usize,
    pub source: String,
    pub labelled_frames: usize,
    pub conf: f32,
    pub iou: f32,
    pub max_det: usize,
    pub classes: Vec<String>,
    #[serde(flatten)]
    pub this: Side,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub compare: Option<Comparison>,
    pub out: String,
    pub seconds: f64,
}

/// What one detector found and how long it took, frame by frame.
struct Collected {
    shown: Vec<Vec<Detection>>,
    eval: Vec<Vec<Detection>>,
    times: [Vec<f64>; 3],
}

impl Collected {
    fn new() -> Collected {
        Collected { shown: Vec::new(), eval: Vec::new(), times: [Vec::new(), Vec::new(), Vec::new()] }
    }

    /// Runs `d` on `frame`: detections above its `conf` (timed), and at validation's threshold
    /// when mAP will be computed.
    fn push(&mut self, d: &mut Detector, frame: &Image, eval: bool) -> Result<()> {
        let out = d.infer(frame)?;
        let t = Instant::now();
        let shown = d.detections(&out, d.conf)?;
        let decode = t.elapsed().as_secs_f64();
        for (k, s) in [out.preprocess, out.inference, decode].into_iter().enumerate() {
            self.times[k].push(s * 1e3);
        }
        self.eval.push(if eval { d.detections(&out, EVAL_CONF.min(d.conf))? } else { Vec::new() });
        self.shown.push(shown);
        Ok(())
    }

    fn side(&self, d: &Detector, labels: Option<&[Vec<Truth>]>) -> Side {
        let classes = d.class_names().len().max(1);
        Side {
            artifact: d.artifact_path.display().to_string(),
            model: d.artifact.model.display().to_string(),
            engine: d.engine,
            why: d.artifact.why.clone(),
            threads: d.threads,
            detections: self.shown.iter().map(Vec::len).sum(),
            latency: latency(d.load_seconds * 1e3, &self.times),
            map_labels: labels.map(|l| coco_map(l, &self.eval, classes)),
        }
    }
}

fn latency(load_ms: f64, times: &[Vec<f64>; 3]) -> Latency {
    let sorted: Vec<Vec<f64>> = times.iter().map(|t| crate::metrics::order::sorted(t.clone())).collect();
    let total: f64 = sorted.iter().map(|s| crate::metrics::order::quantile(s, 0.5)).sum();
    let stage = |s: &[f64]| {
        let median_ms = crate::metrics::order::quantile(s, 0.5);
        StageTimes { median_ms, p95_ms: crate::metrics::order::quantile(s, 0.95), p99_ms: crate::metrics::order::quantile(s, 0.99), share: if total > 0.0 { median_ms / total } else { 0.0 } }
    };
    let summed: f64 = times.iter().flatten().sum();
    Latency { load_ms, preprocess: stage(&sorted[0]), inference: stage(&sorted[1]), decode_nms: stage(&sorted[2]), frames_per_second: if summed > 0.0 { times[0].len() as f64 / (summed / 1e3) } else { 0.0 } }
}

/// Indices of `a`'s detections with no detection of `b` of the same class at IoU ≥ 0.5.
fn unmatched(a: &[Detection], b: &[Detection]) -> Vec<usize> {
    (0..a.len()).filter(|&i| !b.iter().any(|o| o.class == a[i].class && crate::detect::iou(&o.bbox, &a[i].bbox) >= 0.5)).collect()
}

pub fn run(req: &RunRequest) -> Result<RunReport> {
    let started = Instant::now();
    let files = image::list(&req.frames)?;
    let mut this = Detector::load_with(&req.artifact, &req.options)?;
    let mut other = req.compare.as_deref().map(|p| Detector::load_with(p, &Options { engine: None, conf: Some(this.conf), iou: Some(this.iou), max_det: Some(this.max_det), ..req.options.clone() })).transpose()?;
    if let Some(o) = &other {
        if o.scene().is_some_and(|s| s.roi.is_some() || s.object_px.is_some()) && this.scene().is_none() {
            anyhow::bail!("--compare takes the scene-specialized artifact first: run {} --compare {}", o.artifact_path.display(), req.artifact.display());
        }
        if this.scene().is_some_and(|s| s.classes.is_some()) {
            anyhow::bail!("{} keeps some classes of the original: compare it with `verify`, which decodes the original on the kept classes", req.artifact.display());
        }
        if o.class_names().len() != this.class_names().len() {
            anyhow::bail!("{} detects {} classes, {} detects {}: nothing to compare", req.artifact.display(), this.class_names().len(), o.artifact_path.display(), o.class_names().len());
        }
    }
    // Validation's decode (for mAP and agreement) only where something will be scored.
    let eval = other.is_some() || files.iter().any(|f| f.with_extension("txt").is_file());
    let mut labels: Vec<Option<Vec<Truth>>> = Vec::new();
    let mut sizes = Vec::new();
    let staged = StagedDir::new(&req.out)?;
    let dir = staged.path().to_path_buf();
    for sub in ["labels", "images"] {
        std::fs::create_dir(dir.join(sub))?;
    }
    let stems = unique_stems(&files);
    let pb = indicatif::ProgressBar::new(files.len() as u64);
    pb.set_style(indicatif::ProgressStyle::with_template("run {pos}/{len} frames [{bar:30}] {eta} left").unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()));
    let (mut mine, mut theirs) = (Collected::new(), Collected::new());
    let mut sheet = Vec::new();
    let mut images = Vec::new();
    let mut results = Vec::new();
    let (mut only_this, mut only_other) = (0, 0);
    for (i, (path, stem)) in files.iter().zip(&stems).enumerate() {
        let frame = Image::read(path)?;
        let truth = crate::frames::read_yolo_labels(&path.with_extension("txt"), frame.width as f32, frame.height as f32).with_context(|| path.display().to_string())?;
        labels.push(truth);
        sizes.push((frame.height, frame.width));
        mine.push(&mut this, &frame, eval)?;
        let dets = mine.shown.last().expect("pushed").clone();
        let picture = match other.as_mut() {
            None => draw::annotate(&frame, &dets, this.class_names(), &[]),
            Some(o) => {
                theirs.push(o, &frame, eval)?;
                let their = theirs.shown.last().expect("pushed");
                let (a, b) = (unmatched(&dets, their), unmatched(their, &dets));
                (only_this, only_other) = (only_this + a.len(), only_other + b.len());
                let left = draw::annotate(&frame, &dets, this.class_names(), &a);
                let right = draw::annotate(&frame, their, o.class_names(), &b);
                draw::side_by_side(&[(&short(&req.artifact), &left), (&short(&o.artifact_path), &right)])
            }
        };
        write_atomic(&dir.join("images").join(format!("{stem}.png")), &crate::canvas::encode_png(&picture)?)?;
        write_atomic(&dir.join("labels").join(format!("{stem}.txt")), yolo_lines(&dets, &frame).as_bytes())?;
        for d in &dets {
            let name = this.class_name(d.class).to_string();
            results.push(serde_json::json!({ "image_id": i + 1, "file_name": path.file_name().map(|n| n.to_string_lossy().into_owned()), "category_id": d.class, "category_name": name, "bbox": [d.bbox[0], d.bbox[1], d.bbox[2] - d.bbox[0], d.bbox[3] - d.bbox[1]], "score": d.score }));
        }
        images.push(serde_json::json!({ "id": i + 1, "file_name": path.display().to_string(), "width": frame.width, "height": frame.height }));
        if sheet.len() < SHEET_FRAMES {
            sheet.push((stem.clone(), picture));
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let labelled = labels.iter().filter(|l| l.is_some()).count();
    let truths: Option<Vec<Vec<Truth>>> = (labelled > 0).then(|| labels.into_iter().map(Option::unwrap_or_default).collect());
    let this_side = mine.side(&this, truths.as_deref());
    let compare = other.as_ref().map(|o| {
        let classes = this.class_names().len().max(1);
        let (reference, candidate) = match this.scene().filter(|_| o.scene().is_none()) {
            Some(scene) => (in_scene(scene, this.frame_size(), &sizes, &theirs.eval), in_scene(scene, this.frame_size(), &sizes, &mine.eval)),
            None => (theirs.eval.clone(), mine.eval.clone()),
        };
        let (truth, how) = crate::metrics::validation::agreement_truth(&reference, classes);
        Comparison { other: theirs.side(o, truths.as_deref()), agreement: coco_map(&truth, &candidate, classes), truth: how, only_this, only_other }
    });
    let categories: Vec<serde_json::Value> = this.class_names().iter().enumerate().map(|(i, n)| serde_json::json!({ "id": i, "name": n })).collect();
    write_atomic(&dir.join("detections.json"), serde_json::to_string_pretty(&results)?.as_bytes())?;
    let sheet_png = draw::contact_sheet(&sheet, 4, if other.is_some() { 520 } else { 320 });
    write_atomic(&dir.join("contact_sheet.png"), &crate::canvas::encode_png(&sheet_png)?)?;
    let report = RunReport {
        frames: files.len(),
        source: req.frames.display().to_string(),
        labelled_frames: labelled,
        conf: this.conf,
        iou: this.iou,
        max_det: this.max_det,
        classes: this.class_names().to_vec(),
        this: this_side,
        compare,
        out: req.out.display().to_string(),
        seconds: started.elapsed().as_secs_f64(),
    };
    let mut json = serde_json::to_value(&report)?;
    json["images"] = serde_json::Value::Array(images);
    json["categories"] = serde_json::Value::Array(categories);
    write_atomic(&dir.join("run.json"), serde_json::to_string_pretty(&json)?.as_bytes())?;
    staged.commit()?;
    Ok(report)
}

/// Detections a scene-specialized model is compared on, as `verify` compares it: kept classes
/// and sizes, inside the ROI by the full model's coarsest stride (judged in the model's frame).
fn in_scene(scene: &crate::scene::SceneMeta, model_frame: (usize, usize), sizes: &[(usize, usize)], dets: &[Vec<Detection>]) -> Vec<Vec<Detection>> {
    let margin = if scene.roi.is_some() { scene.full_strides.iter().copied().max().unwrap_or(0) as f32 } else { 0.0 };
    dets.iter()
        .zip(sizes)
        .map(|(ds, &(h, w))| {
            let (sx, sy) = (model_frame.1 as f32 / w as f32, model_frame.0 as f32 / h as f32);
            ds.iter().filter(|d| scene.keeps(d.class, &[d.bbox[0] * sx, d.bbox[1] * sy, d.bbox[2] * sx, d.bbox[3] * sy], margin)).copied().collect()
        })
        .collect()
}

/// The last path component, for picture titles.
fn short(p: &Path) -> String {
    p.file_name().map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into_owned())
}

/// File stems, made unique (`a.png` and `a.tif` become `a` and `a.tif`).
fn unique_stems(files: &[PathBuf]) -> Vec<String> {
    let mut seen = std::collections::HashSet::new();
    files
        .iter()
        .map(|p| {
            let stem = p.file_stem().map_or_else(String::new, |s| s.to_string_lossy().into_owned());
            if seen.insert(stem.clone()) {
                stem
            } else {
                let full = p.file_name().map_or_else(String::new, |s| s.to_string_lossy().into_owned());
                seen.insert(full.clone());
                full
            }
        })
        .collect()
}

/// YOLO label lines (`class cx cy w h score`, normalized) of detections on `frame`.
fn yolo_lines(dets: &[Detection], frame: &Image) -> String {
    let (w, h) = (frame.width as f32, frame.height as f32);
    dets.iter()
        .map(|d| {
            let [x1, y1, x2, y2] = d.bbox;
            format!("{} {:.6} {:.6} {:.6} {:.6} {:.5}\n", d.class, (x1 + x2) / 2.0 / w, (y1 + y2) / 2.0 / h, (x2 - x1) / w, (y2 - y1) / h, d.score)
        })
        .collect()
}

impl RunReport {
    /// The screen a person reads.
    pub fn render(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let side = |s: &mut String, x: &Side| {
            let l = &x.latency;
            let _ = writeln!(s, "{} on {:?}, {} thread(s): {}", x.artifact, x.engine, x.threads, x.why);
            let _ = writeln!(
                s,
                "  {} detections; {:.1} frames/s; per frame: pre-process {:.2} ms ({:.0}%), inference {:.2} ms ({:.0}%), decode + NMS {:.2} ms ({:.0}%); load {:.0} ms",
                x.detections,
                l.frames_per_second,
                l.preprocess.median_ms,
                l.preprocess.share * 100.0,
                l.inference.median_ms,
                l.inference.share * 100.0,
                l.decode_nms.median_ms,
                l.decode_nms.share * 100.0,
                l.load_ms
            );
            if let Some(m) = &x.map_labels {
                let _ = writeln!(s, "  mAP against labels: @0.5 {:.4}, @0.5:0.95 {:.4}", m.map50, m.map50_95);
            }
        };
        let _ = writeln!(s, "run on {} frame(s) from {} ({} with labels); conf {}, IoU {}, max {} per frame", self.frames, self.source, self.labelled_frames, self.conf, self.iou, self.max_det);
        side(&mut s, &self.this);
        if let Some(c) = &self.compare {
            side(&mut s, &c.other);
            let _ = writeln!(s, "agreement with {}: mAP@0.5:0.95 {:.4}, @0.5 {:.4}; {} box(es) only in the first, {} only in the second (magenta)", c.other.artifact, c.agreement.map50_95, c.agreement.map50, c.only_this, c.only_other);
        }
        let _ = writeln!(s, "wrote {}: detections.json, labels/, images/, contact_sheet.png, run.json", self.out);
        s
    }
}
