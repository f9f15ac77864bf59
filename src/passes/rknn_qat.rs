//! `rknn-qat`: quantization-aware recovery for the RK3588 NPU, on RKNN-Toolkit2's own
//! quantization plan.
//!
//! Needs: a model from `rknn-legalize` (float, per-stride outputs), no `rknn-hybrid` spans,
//! RKNN-Toolkit2 (its venv, installed on first use) and PyTorch (the recovery worker's).
//! Frames come from `--calib` or the physics pipeline, fed as 8-bit pixels as the NPU gets
//! them.
//!
//! The toolkit does not read a QDQ graph, and its plan is not ours (`targets::rknn_points`:
//! fused Conv+ReLU, SiLU as one op, int8 image and outputs, int16 gate products). So the pass
//! asks the toolkit for its plan (hybrid-quantization step 1 on the calibration frames that
//! `--target rknn` writes), emits a QDQ model with int8 pairs exactly at its int8 points and
//! its per-channel 8-bit weights, trains that model's integers against the float model in the
//! torch worker (the `quantize` pass's QAT), and writes the trained integers back as float
//! weights the toolkit requantizes to the same integers: weights at ±127 stay there, so each
//! channel's peak, and with it the toolkit's per-channel scale, is unchanged. The image point
//! gets the exact 8-bit pixel grid ([0, 1] in steps of 1/255) instead of the calibrated range,
//! which would clip the brightest pixels the calibration frames lack.
//!
//! Guarantees: the graph is unchanged; only Conv weights and biases change, and only if the
//! worst output's error against float on held-out frames improves (outputs that never move
//! by one int8 output step have no say; otherwise the model is left as it came). The trained points go into metadata (`pdi.rknn_trained_points`);
//! `--target rknn` copies them into rknn.yaml and `rknn-convert` writes them into the
//! toolkit's quantization config before it builds.
//! Reports: the toolkit's points (trained, left to the toolkit and why), the training account,
//! and the held-out rel L2 per output of the QDQ model against float before and after.

use super::prune::by_name;
use crate::calib_frames::{calibration_frames, replicate};
use crate::detect::split_head::HeadLayout;
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use crate::quant::at_points;
use crate::quant::attribution::{worst_rel_l2, OutputError, ReferenceOutputs};
use ort::session::builder::GraphOptimizationLevel;
use crate::quant::qat::{self, Student};
use crate::targets::rknn::DATASET_FRAMES;
use crate::targets::rknn_toolkit::npu_input;
use crate::targets::rknn_convert::OUTPUT_STEP;
use crate::targets::rknn_points::{self, Point};
use crate::tensor::Tensor;
use crate::torch::schedule::Schedule;
use anyhow::{anyhow, bail, Result};
use std::collections::BTreeMap;

/// Unknown options are refused where options are read (`passes::with`).
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct Options {
    #[serde(flatten)]
    pub schedule: Schedule,
    /// Training frames (fresh augmentation each epoch).
    pub frames: usize,
    /// Seed of frame order, augmentation and the simulated frames.
    pub seed: u64,
}

impl Options {
    /// The ranges, checked when the recipe loads.
    pub fn check(&self) -> Result<()> {
        self.schedule.check("")?;
        if self.frames < self.schedule.batch {
            bail!("rknn-qat has {} frames for batches of {}; raise frames or lower batch", self.frames, self.schedule.batch);
        }
        Ok(())
    }
}

impl Default for Options {
    fn default() -> Self {
        Options { schedule: Schedule::new(800, 1e-4, 8), frames: 64, seed: 0 }
    }
}

/// Frames held out to judge the training (their own seed: neither calibration nor training).
const HELD_OUT: usize = 8;
const HELD_OUT_SEED: u64 = 7_000_001;

pub struct RknnQat {
    pub options: Options,
}

impl Pass for RknnQat {
    fn name(&self) -> &'static str {
        "rknn-qat"
    }

    fn check(&self) -> Result<()> {
        self.options.check()
    }

    fn needs(&self) -> Vec<super::Capability> {
        vec![super::Capability::SplitHead]
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let o = &self.options;
        let layout = HeadLayout::from_model(model).map_err(|_| anyhow!("rknn-qat needs a model from rknn-legalize: put it after rknn-legalize in the recipe"))?;
        if !crate::targets::rknn_fp16::stored(model)?.is_empty() {
            bail!("rknn-qat trains every layer in INT8, and this model has rknn-hybrid's FP16 spans: drop rknn-hybrid from the recipe");
        }
        let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let (input, shape) = crate::ir::shapes::static_image_input(g, "rknn-qat")?;
        let npu_frames = |n: usize, seed: u64| -> Result<Vec<Tensor>> {
            let set = calibration_frames(cx.calib.as_deref(), n, shape[2], shape[3], seed)?;
            Ok(set.frames.iter().map(|f| replicate(&Tensor::f32(f.image.shape.clone(), npu_input(f.image.as_f32().unwrap_or(&[]))), shape[1])).collect())
        };
        // The frames `--target rknn` writes for the toolkit (same count, same seed).
        let calibration = npu_frames(DATASET_FRAMES, 0)?;
        let frames = npu_frames(o.frames, o.seed)?;
        let held: Vec<Vec<(String, Tensor)>> = npu_frames(HELD_OUT, HELD_OUT_SEED)?.into_iter().map(|f| vec![(input.clone(), f)]).collect();

        let toolkit = rknn_points::toolkit_points(model, &calibration, &layout.output_names())?;
        let is_int8 = |v: &str| toolkit.get(v).is_some_and(|p| p.int8().is_some());
        // Values the emitted model has: the graph's, and the partial sums of the convolutions
        // the toolkit splits per concatenated input.
        let splits = at_points::splits(g, is_int8);
        let values: std::collections::HashSet<&str> = g.node.iter().flat_map(|n| n.output.iter()).chain(std::iter::once(&input)).chain(&splits.sums).map(String::as_str).collect();
        // Trained points by graph value, and the toolkit's name for each. The toolkit keeps
        // the graph's input and outputs as float32 entries and quantizes them under
        // `<name>_int8`; the image gets the exact pixel grid instead of its calibrated range.
        let mut trained: BTreeMap<String, (String, Point)> = BTreeMap::new();
        let mut left: BTreeMap<String, String> = BTreeMap::new();
        for (name, p) in &toolkit {
            let border = name.strip_suffix("_int8").filter(|v| toolkit.get(*v).is_some_and(|b| b.dtype == "float32") && values.contains(v));
            match (border, p.int8()) {
                (Some(v), Some(_)) if v == input => {
                    trained.insert(v.to_string(), (name.clone(), Point::int8_covering(0.0, 1.0)));
                }
                (Some(v), Some(_)) => {
                    trained.insert(v.to_string(), (name.clone(), p.clone()));
                }
                (None, Some(_)) if values.contains(name.as_str()) => match rknn_points::fused_away(g, name, &splits.outputs) {
                    Some(why) => {
                        left.insert(name.clone(), why.to_string());
                    }
                    None => {
                        trained.insert(name.clone(), (name.clone(), p.clone()));
                    }
                },
                _ if p.dtype == "float32" && values.contains(name.as_str()) => {}
                _ if !values.contains(name.as_str()) => {
                    left.insert(name.clone(), format!("{} (the toolkit's own tensor, not in the ONNX graph)", p.dtype));
                }
                _ => {
                    left.insert(name.clone(), format!("{} (not an int8 point)", p.dtype));
                }
            }
        }
        let params: BTreeMap<String, (f64, i32)> = trained.iter().filter_map(|(v, (_, p))| Some((v.clone(), p.int8()?))).collect();
        let (quantized, dequantized) = at_points::emit(model, &params)?;

        let heads = crate::torch::heads::split_head_specs(model, &dequantized)?;
        let training = qat::training(&o.schedule, o.seed);
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let student = Student { heads, scale_groups: Vec::new(), scale_lr: 1.0, weight_range: at_points::WEIGHT_RANGE, pin_extremes: true };
        let t = qat::train(&quantized, model, student, &frames, &held, &training, threads)?;
        cx.record_training(&t.outcome);
        // The NPU sums in exact int32: ONNX Runtime's reference kernels compute what it does,
        // its x86 integer kernels do not (they saturate with 8-bit weights without VNNI).
        let reference = ReferenceOutputs::new(model, &held, threads, None)?;
        let (before, after) = (reference.errors_at(&quantized, GraphOptimizationLevel::Disable)?, reference.errors_at(&t.model, GraphOptimizationLevel::Disable)?);
        // Outputs that never move by one int8 output step (a level with no object in the
        // held-out frames: float scores ~1e-5, the QDQ's 0, rel L2 1 either way) have no say.
        let signal = |e: &OutputError| e.error.max_abs >= OUTPUT_STEP;
        let judged: std::collections::HashSet<&str> = before.iter().chain(&after).filter(|e| signal(e)).map(|e| e.output.as_str()).collect();
        let worst = |errors: &[OutputError]| worst_rel_l2(&errors.iter().filter(|e| judged.contains(e.output.as_str())).cloned().collect::<Vec<_>>());
        let kept = worst(&after) < worst(&before);
        if kept {
            *model = at_points::dequantized_weights(model, &t.model)?;
            let stored = trained.iter().map(|(v, (name, p))| (name.clone(), Point { value: Some(v.clone()), ..p.clone() })).collect();
            rknn_points::store(model, &stored)?;
        }
        Ok(serde_json::json!({
            "kept": kept,
            "judged_outputs": judged,
            "toolkit_points": toolkit.len(),
            "image_point": "the 8-bit pixel grid: [0, 1] in steps of 1/255",
            "trained_points": trained.len(),
            "left_to_the_toolkit": left,
            "frames": frames.len(),
            "held_out_frames": held.len(),
            "qdq_vs_float_rel_l2": { "before": by_name(&before), "after": by_name(&after) },
            "emitted_vs_fake_quant_rel_l2": t.reproduced,
            "not_reproducible": t.outcome.not_reproducible(),
            "training": t.outcome,
        }))
    }
}
