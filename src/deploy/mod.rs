//! Running what the toolchain ships, as a camera application would: load an artifact, turn a
//! camera frame into the model's input as the artifact says, run it, decode the head the
//! toolchain emitted, suppress duplicates. `pdi-compile run` and embedding code share this
//! one path, so the boxes a user draws are the boxes `verify` scored.
//!
//! ```no_run
//! use pdi_compile::deploy::{Detector, Image};
//! # fn main() -> anyhow::Result<()> {
//! let mut detector = Detector::load("shipped/pruned-int8")?;
//! let frame = Image::read("frames/0001.png")?;
//! for d in detector.detect(&frame)? {
//!     println!("{} {:.2} at {:?}", detector.class_name(d.class), d.score, d.bbox);
//! }
//! # Ok(())
//! # }
//! ```

pub mod artifact;
pub mod draw;
pub mod image;
pub mod input;

pub use artifact::Artifact;
pub use image::Image;

use crate::analysis::head::{Head, HeadKind};
use crate::detect::split_head::{self, HeadLayout};
use crate::detect::{decode, nms::nms, Detection};
use crate::runtime::{self, Engine, Runtime};
use crate::scene::SceneMeta;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// A deployment's usual score cut (ultralytics predict's default).
pub const DEFAULT_CONF: f32 = 0.25;

pub use crate::metrics::validation::{default_iou, DEFAULT_MAX_DET, EVAL_CONF};

/// How to run an artifact; `None` takes the artifact's own choice (its recommended engine,
/// tract's fastest thread count, the scene's score threshold and detection cap).
#[derive(Clone, Debug, Default)]
pub struct Options {
    pub engine: Option<Engine>,
    pub threads: Option<usize>,
    pub conf: Option<f32>,
    pub iou: Option<f32>,
    pub max_det: Option<usize>,
    /// The camera's blur map, for a model that still takes it as an input.
    pub psf: Option<PathBuf>,
}

/// What the model's output is decoded with.
enum Decoder {
    /// An in-graph decoded head ([1, N, 5+nc] or [1, 4+nc, N]).
    Dense(Head),
    /// The RKNN-legalized split head, decoded from its per-level tensors.
    Split(HeadLayout),
}

/// A model's outputs for one frame, and the seconds its first two stages took.
pub struct Outputs {
    /// By output name (the split head's decode looks its tensors up by name).
    pub tensors: HashMap<String, Tensor>,
    /// The camera frame's (height, width).
    pub size: (usize, usize),
    pub preprocess: f64,
    pub inference: f64,
}

/// A loaded artifact, ready for frames.
pub struct Detector {
    /// The path it was loaded from, and what it turned out to be.
    pub artifact_path: PathBuf,
    pub artifact: Artifact,
    pub engine: Engine,
    pub threads: usize,
    /// Score threshold, NMS IoU and detection cap of [`Detector::detect`].
    pub conf: f32,
    pub iou: f32,
    pub max_det: usize,
    /// Seconds to load the model into its engine.
    pub load_seconds: f64,
    image_input: String,
    channels: usize,
    /// The frame the model's boxes are in: (height, width) of the full input, before any ROI crop.
    frame: (usize, usize),
    scene: Option<SceneMeta>,
    other_inputs: Vec<(String, Tensor)>,
    decoder: Decoder,
    names: Vec<String>,
    runtime: Box<dyn Runtime>,
}

impl Detector {
    /// Loads an artifact (a folder `compile` or `ship` wrote, or a model file) with its own
    /// settings.
    pub fn load(path: impl AsRef<Path>) -> Result<Detector> {
        Detector::load_with(path.as_ref(), &Options::default())
    }

    pub fn load_with(path: &Path, opts: &Options) -> Result<Detector> {
        let artifact = Artifact::open(path)?;
        let model = crate::onnx::load(&artifact.model)?.model;
        let side = input::ModelInput::of(&model, "the artifact's model")?;
        let scene = SceneMeta::read(&model)?;
        let frame = scene.as_ref().map_or(side.shape, |s| (s.frame[0], s.frame[1]));
        let expected = scene.as_ref().and_then(|s| s.roi).map_or(frame, |r| (r.h, r.w));
        if expected != side.shape {
            bail!("the model takes {:?} frames but its scene says {:?}", side.shape, expected);
        }
        let head = crate::inspect::inspect(&model)?.head;
        let decoder = if model.metadata_props.iter().any(|p| p.key == split_head::METADATA_KEY) {
            Decoder::Split(HeadLayout::from_model(&model)?)
        } else if head.kind != HeadKind::Raw && head.output.is_some() {
            Decoder::Dense(head.clone())
        } else {
            bail!("{}: the model has no decoded YOLOv5/YOLOv8 output and no split-head layout to decode", artifact.model.display());
        };
        let (kind, classes) = match &decoder {
            Decoder::Dense(h) => (h.kind, h.classes.unwrap_or(0)),
            Decoder::Split(l) => (l.kind, l.classes),
        };
        let names = crate::scene::class_names(&model).filter(|n| n.len() == classes).unwrap_or_else(|| (0..classes).map(|i| i.to_string()).collect());
        let blur = opts.psf.as_deref().map(input::blur_input).transpose()?;
        let other_inputs = side
            .other_inputs
            .iter()
            .map(|n| Ok((n.clone(), blur.clone().ok_or_else(|| anyhow!("the model's input '{n}' takes the camera's blur map: give it with --psf (or compile with bind-psf)"))?)))
            .collect::<Result<Vec<_>>>()?;
        let engine = opts.engine.unwrap_or(artifact.engine);
        let threads = opts.threads.or(artifact.threads).unwrap_or_else(runtime::all_cores);
        if threads == 0 {
            bail!("--threads must be at least 1");
        }
        let post = artifact.post;
        let conf = opts.conf.or(post.map(|p| p.0)).or(scene.as_ref().and_then(|s| s.score_threshold)).unwrap_or(DEFAULT_CONF);
        let iou = opts.iou.or(post.map(|p| p.1)).unwrap_or_else(|| default_iou(kind));
        let max_det = opts.max_det.or(post.map(|p| p.2)).or(scene.as_ref().and_then(|s| s.max_detections)).unwrap_or(DEFAULT_MAX_DET);
        if !(0.0..1.0).contains(&conf) || !(0.0..=1.0).contains(&iou) || max_det == 0 {
            bail!("--conf must be in [0, 1), --iou in [0, 1] and --max-det at least 1 (got {conf}, {iou}, {max_det})");
        }
        // The runtime is built with a feed of the input's shape: engines fix shapes up front.
        let (h, w) = side.shape;
        let mut first = vec![(side.image_input.clone(), Tensor::f32(vec![1, side.channels, h, w], vec![0.0; side.channels * h * w]))];
        first.extend(other_inputs.iter().cloned());
        let t = Instant::now();
        let runtime = runtime::load(engine, &model, &first, threads)?;
        Ok(Detector {
            engine,
            threads,
            conf,
            iou,
            max_det,
            load_seconds: t.elapsed().as_secs_f64(),
            image_input: side.image_input,
            channels: side.channels,
            frame,
            scene,
            other_inputs,
            decoder,
            names,
            runtime,
            artifact_path: path.to_path_buf(),
            artifact,
        })
    }

    /// Detections on one frame above the detector's `conf`, in the frame's own pixel
    /// coordinates, best first.
    pub fn detect(&mut self, frame: &Image) -> Result<Vec<Detection>> {
        let out = self.infer(frame)?;
        self.detections(&out, self.conf)
    }

    /// The model's outputs for one frame, with the time its pre-processing and inference took.
    pub fn infer(&mut self, frame: &Image) -> Result<Outputs> {
        let t0 = Instant::now();
        let feeds = self.feeds(frame)?;
        let t1 = Instant::now();
        let tensors = self.runtime.run(&feeds)?;
        let inference = t1.elapsed().as_secs_f64();
        Ok(Outputs { tensors: tensors.into_iter().collect(), size: (frame.height, frame.width), preprocess: (t1 - t0).as_secs_f64(), inference })
    }

    /// Detections above `conf` (validation decodes at [`EVAL_CONF`]) after class-aware NMS,
    /// scaled from the model's frame back to the camera frame's pixels. Boxes are not clipped
    /// to the frame, as validation scores them.
    pub fn detections(&self, out: &Outputs, conf: f32) -> Result<Vec<Detection>> {
        let (h, w) = out.size;
        let (sx, sy) = (w as f32 / self.frame.1 as f32, h as f32 / self.frame.0 as f32);
        let dets = self.decode(&out.tensors, conf)?;
        if (sx, sy) == (1.0, 1.0) {
            return Ok(dets);
        }
        Ok(dets.into_iter().map(|d| Detection { bbox: [d.bbox[0] * sx, d.bbox[1] * sy, d.bbox[2] * sx, d.bbox[3] * sy], ..d }).collect())
    }

    /// The name of class `c` (from the export's `names`, else its index).
    pub fn class_name(&self, c: usize) -> &str {
        self.names.get(c).map_or("?", String::as_str)
    }

    pub fn class_names(&self) -> &[String] {
        &self.names
    }

    /// The (height, width) frames are resized to, before any ROI crop.
    pub fn frame_size(&self) -> (usize, usize) {
        self.frame
    }

    /// The scene the artifact was specialized for (classes, object sizes, ROI), if any.
    pub fn scene(&self) -> Option<&SceneMeta> {
        self.scene.as_ref()
    }

    /// The model's inputs for `frame`: area-resized to the model's frame, its ROI cropped,
    /// replicated into the image input's channels, the blur map beside it where it is an input.
    fn feeds(&self, frame: &Image) -> Result<Vec<(String, Tensor)>> {
        let (h, w) = self.frame;
        let data = if (frame.height, frame.width) == (h, w) { frame.data.clone() } else { crate::frames::resize_area(&frame.data, frame.width, frame.height, w, h) };
        let mut image = Tensor::f32(vec![1, 1, h, w], data);
        if let Some(r) = self.scene.as_ref().and_then(|s| s.roi) {
            image = r.crop(&image).ok_or_else(|| anyhow!("the frame does not hold the ROI"))?;
        }
        let mut v = vec![(self.image_input.clone(), crate::calib_frames::replicate(&image, self.channels))];
        v.extend(self.other_inputs.iter().cloned());
        Ok(v)
    }

    /// Detections above `conf` after class-aware NMS, in the model's frame coordinates.
    fn decode(&self, outputs: &HashMap<String, Tensor>, conf: f32) -> Result<Vec<Detection>> {
        match &self.decoder {
            Decoder::Dense(head) => {
                let name = head.output.as_deref().unwrap_or_default();
                let t = outputs.get(name).ok_or_else(|| anyhow!("output {name} missing"))?;
                Ok(nms(decode::candidates(head.kind, t, conf)?, self.iou, self.max_det))
            }
            Decoder::Split(layout) => Ok(split_head::detect(layout, outputs, conf, self.iou, self.max_det)?.0),
        }
    }
}
