//! `--target rknn`: what RKNN-Toolkit2 needs to build model.rknn for the RK3588 NPU.
//!
//! DIR/rknn.yaml       the toolkit's configuration (platform, preprocessing, quantization,
//!                     outputs, head layout for post-processing); edit it, then run
//!                     `pdi-compile rknn-convert DIR`
//! DIR/dataset.txt     the calibration frames, one .npy per line (relative to DIR)
//! DIR/calib/*.npy     those frames, [1, 1, H, W] float32 in 0..255
//! DIR/run_rknn.py     runs model.rknn on the board (RKNNLite) or the toolkit's simulator:
//!                     the pre-processing and decoding of `pdi-compile run`, in Python
//!
//! The model must come out of `rknn-legalize` (float, per-stride outputs, head layout in its
//! metadata): the toolkit quantizes it itself, from these frames.

use super::rknn_toolkit::{pixels, PIXEL_SCALE};
use crate::calib_frames::calibration_frames;
use crate::detect::split_head::HeadLayout;
use crate::fsutil::{ensure_dir, write_atomic};
use crate::onnx::proto::ModelProto;
use anyhow::{anyhow, bail, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Calibration frames written for the toolkit (more adds build time, not accuracy, on
/// models this size: measured cosine is flat from 16 frames up).
pub const DATASET_FRAMES: usize = 32;
/// Highest ONNX IR version RKNN-Toolkit2 2.5 reads.
pub const MAX_IR_VERSION: i64 = 9;

/// DIR/rknn.yaml: read back by `rknn-convert`.
#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct RknnConfig {
    pub target_platform: String,
    pub model: String,
    pub input: RknnInput,
    pub quantization: RknnQuantization,
    pub outputs: Vec<String>,
    pub head_layout: HeadLayout,
    /// Class names in output order (the export's `names`, else indices).
    #[serde(default)]
    pub names: Vec<String>,
    /// A scene's ROI: frames are resized to `frame` and `roi` cut out before the NPU sees them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop: Option<Crop>,
    /// What the application's post-processing applies (a scene's settings, else YOLO's
    /// deployment defaults); `rknn-convert` matches detections with them.
    #[serde(default)]
    pub post_processing: PostProcessing,
}

#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct Crop {
    /// (height, width) of the frame the model's boxes are in.
    pub frame: [usize; 2],
    /// x, y, width, height in that frame.
    pub roi: [usize; 4],
}

/// The board's runner, written beside the model.
pub const RUN_RKNN: &str = include_str!("run_rknn.py");

#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct PostProcessing {
    pub score_threshold: f32,
    pub nms_iou: f32,
    pub max_detections: usize,
}

impl Default for PostProcessing {
    fn default() -> Self {
        PostProcessing { score_threshold: 0.25, nms_iou: 0.45, max_detections: 300 }
    }
}

impl PostProcessing {
    /// The defaults, overridden by what the model's scene says.
    pub fn of(model: &crate::onnx::proto::ModelProto) -> Result<PostProcessing> {
        let d = PostProcessing::default();
        Ok(match crate::scene::SceneMeta::read(model)? {
            Some(s) => PostProcessing { score_threshold: s.score_threshold.unwrap_or(d.score_threshold), max_detections: s.max_detections.unwrap_or(d.max_detections), ..d },
            None => d,
        })
    }
}

#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct RknnInput {
    pub name: String,
    pub shape: [usize; 4],
    /// Per channel; the NPU computes (pixel − mean) / std before the first layer.
    pub mean_values: Vec<Vec<f32>>,
    pub std_values: Vec<Vec<f32>>,
    /// The range the NPU quantizes the normalized input over (its `<input>_int8` tensor).
    /// [0, 1] puts every 8-bit pixel on a step of its own (q = pixel − 128); absent, the
    /// toolkit calibrates it, [0, 0.84] on the simulated frames, and clips brighter pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub range: Option<[f64; 2]>,
}

#[derive(Serialize, Deserialize, Clone, Debug)]
pub struct RknnQuantization {
    pub do_quantization: bool,
    /// RKNN-Toolkit2 names: w8a8, w8a16, w16a16i.
    pub quantized_dtype: String,
    /// normal (min/max), mmse, kl_divergence.
    pub quantized_algorithm: String,
    /// channel (per-channel weights) or layer.
    pub quantized_method: String,
    /// Let the toolkit raise layers whose simulated output cosine falls below
    /// `auto_hybrid_cos_thresh` to 16 bits (RKNN's mixed precision).
    #[serde(default)]
    pub auto_hybrid: bool,
    #[serde(default = "default_hybrid_cosine")]
    pub auto_hybrid_cos_thresh: f64,
    /// Layers to keep in FP16 (the rknn-hybrid pass's choice; empty: all INT8). Each span
    /// from `input` to `output` becomes one of the toolkit's custom hybrid spans.
    #[serde(default)]
    pub fp16_layers: Vec<crate::targets::rknn_fp16::Fp16Layer>,
    pub dataset: String,
    pub dataset_frames: usize,
    pub dataset_source: String,
    /// Quantization points the model was trained on (`rknn-qat`), by the toolkit's tensor
    /// names: `rknn-convert` writes them into the toolkit's quantization config in place of
    /// its own calibration. Empty: the toolkit calibrates every tensor itself.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub trained_points: std::collections::BTreeMap<String, super::rknn_points::Point>,
}

pub fn write(dir: &Path, model: &ModelProto, calib: Option<&Path>) -> Result<RknnConfig> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let layout = HeadLayout::from_model(model).map_err(|_| {
        anyhow!("the rknn target needs a model from the rknn-legalize pass (per-stride outputs, no decode): compile with passes/detect-rknn.yaml or passes/detect-pruned-rknn.yaml")
    })?;
    if model.ir_version > MAX_IR_VERSION {
        bail!("IR version {} is above RKNN-Toolkit2's {MAX_IR_VERSION}; rknn-legalize lowers it: keep it last in the recipe", model.ir_version);
    }
    if let Some(n) = g.node.iter().find(|n| matches!(n.op_type.as_str(), "QuantizeLinear" | "DequantizeLinear" | "Cast")) {
        bail!("node '{}' ({}) is not float: RKNN-Toolkit2 quantizes the float model itself; drop quantize/fp16 from the recipe", n.name, n.op_type);
    }
    let (name, shape) = crate::ir::shapes::static_image_input(g, "the rknn target")?;
    let frames = calibration_frames(calib, DATASET_FRAMES, shape[2], shape[3], 0)?;
    let calib_dir = dir.join("calib");
    ensure_dir(&calib_dir)?;
    let mut list = String::new();
    for (i, f) in frames.frames.iter().enumerate() {
        let file = format!("calib/frame_{i:03}.npy");
        write_atomic(&dir.join(&file), &crate::optics::npy::to_bytes(&f.image.shape, &pixels(f.image.as_f32().unwrap_or(&[]))))?;
        list.push_str(&file);
        list.push('\n');
    }
    write_atomic(&dir.join("dataset.txt"), list.as_bytes())?;
    let config = RknnConfig {
        target_platform: "rk3588".into(),
        model: "model.onnx".into(),
        input: RknnInput { name, shape, mean_values: vec![vec![0.0; shape[1]]], std_values: vec![vec![PIXEL_SCALE; shape[1]]], range: Some([0.0, 1.0]) },
        quantization: RknnQuantization {
            do_quantization: true,
            quantized_dtype: "w8a8".into(),
            quantized_algorithm: "normal".into(),
            quantized_method: "channel".into(),
            auto_hybrid: false,
            auto_hybrid_cos_thresh: default_hybrid_cosine(),
            fp16_layers: crate::targets::rknn_fp16::stored(model)?,
            dataset: "dataset.txt".into(),
            dataset_frames: frames.frames.len(),
            dataset_source: frames.source,
            trained_points: super::rknn_points::stored(model)?,
        },
        outputs: layout.output_names(),
        names: crate::scene::class_names(model).filter(|n| n.len() == layout.classes).unwrap_or_else(|| (0..layout.classes).map(|i| i.to_string()).collect()),
        crop: crate::scene::SceneMeta::read(model)?.and_then(|s| s.roi.map(|r| Crop { frame: s.frame, roi: [r.x, r.y, r.w, r.h] })),
        head_layout: layout,
        post_processing: PostProcessing::of(model)?,
    };
    write_atomic(&dir.join("rknn.yaml"), yaml_serde::to_string(&config)?.as_bytes())?;
    write_atomic(&dir.join("run_rknn.py"), RUN_RKNN.as_bytes())?;
    Ok(config)
}

/// The toolkit's own default.
fn default_hybrid_cosine() -> f64 {
    0.98
}

