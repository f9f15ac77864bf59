//! `recover`: recovery of a pruned detector by distillation from the unpruned one.
//!
//! Needs: a `prune` pass earlier in the recipe (it leaves the unpruned model as the teacher)
//! or a scene pass (the unspecialized model, on full frames when the scene crops),
//! a YOLOv5 or YOLOv8 head, and PyTorch (the cache's torch venv, installed on first use;
//! `PDI_TORCH_PYTHON` points at another). Frames come from `--calib` or the physics pipeline;
//! no labels are read. Trains on a CUDA GPU when torch sees one, else on the CPU. Frames larger
//! than 256x192 train whole, the batch counted in frames of 256x192 (`crop: auto`: 2 frames of
//! 640x480 a step for a batch of 8); `crop: WxH` trains on random crops instead, the folded
//! gate maps cut with each; the held-out judgement runs on whole frames.
//! Guarantees: only initializer values change (nodes, names, shapes and types are checked);
//! the PSF gate maps, upsampling kernels and decode constants stay as they were (only Conv
//! weights and biases train; with `train: estimates` only the constants of `crop-roi`'s
//! halos and pool corrections, every weight of the network staying as it was); the trained
//! values are kept only when they agree better with the teacher's detections on held-out
//! frames (mAP@0.5:0.95 against its confident boxes; on a tie, under a scene, or without a
//! decodable head: when they bring the worst output group closer to the teacher's).
//! Reports: the loss per epoch, device, steps, frames/s and seconds, the crop, the box terms' weights,
//! the rel L2 per output group and the detection agreement against the teacher on held-out
//! frames before and after.

use crate::calib_frames::{affordable_frames, image_feeds};
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use super::prune::by_name;
use super::{Pass, PassContext, Teacher};
use crate::tensor::Tensor;
use crate::torch::heads::{feature_specs, head_specs_against};
use crate::torch::schedule::Schedule;
use crate::torch::train::{train, Job, Outcome, Training};
use std::collections::HashMap;
use crate::quant::attribution::{worst_rel_l2, DetectionAgreement, ReferenceOutputs};
use crate::scene::compare::SceneView;
use anyhow::{anyhow, bail, Result};

/// Unknown options are refused where options are read (`passes::with`): serde cannot deny
/// them beside a flattened field.
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct Options {
    #[serde(flatten)]
    pub schedule: Schedule,
    /// Training frames (unlabelled), at most what fits in 2 GiB of pixels; 16 more are held
    /// out to judge the result.
    pub frames: usize,
    /// Seed of frame order, augmentation and the simulated frames.
    pub seed: u64,
    /// What trains: every Conv weight and bias (`all`), or only the constants `crop-roi`
    /// fitted, its halos and pool corrections (`estimates`), the network's weights fixed.
    pub train: Train,
    /// Weight of the YOLOv8 box edges' own error (each side's expected distance, in DFL
    /// bins) beside the distributions' KL: pruning blurs the edges by fractions of a bin,
    /// which the KL barely sees and mAP at IoU 0.95 does. 0: the KL alone. 16 because the
    /// pruned width-0.25 v8's recovered mAP@0.5:0.95 rose with it, 0.654 / 0.679 / 0.708 /
    /// 0.728 at 0 / 1 / 4 / 16, then levelled off (0.731 at 64; 19 minutes each, 2 CPU
    /// cores). YOLOv5 heads do not read it.
    pub box_edges: f64,
    /// Weight of the YOLOv8 class scores' KL on the cells where the teacher sees an object
    /// (weighted by its best class score), beside the KL's plain mean over every cell: the
    /// background's cells outnumber the objects' about a hundredfold and decide that mean,
    /// while mAP ranks the objects' scores. 0: the mean alone. YOLOv5 heads do not read it.
    pub class_foreground: f64,
    /// Weight of the YOLOv5 box sides' absolute error beside the squared error of its
    /// sigmoid box terms (the centre in grid cells, the size as a log ratio, weighted by the
    /// teacher's objectness): a squared error's gradient fades as the boxes come close, where
    /// mAP at IoU 0.95 still sees them, as with YOLOv8's box edges. 0: off. 16 because the
    /// pruned width-0.25 v5's recovered mAP@0.5:0.95 rose with it from 0.897x to 0.982x of
    /// the unpruned model's in the same 8000 steps. YOLOv8 heads do not read it.
    pub v5_box_edges: f64,
    /// Weight of 1 − IoU between the student's and the teacher's YOLOv8 boxes (each side's
    /// expected distance; both boxes share the cell's anchor point), weighted by the
    /// teacher's best class score, beside the box edges: an edge's error in bins costs a
    /// small box more IoU than a large one, and the IoU counts it so, as the detector's own
    /// loss does. 0: off. 64 because the pruned width-0.25 v8's recovered mAP@0.5:0.95 rose
    /// with it from 0.886x to 0.929x of the unpruned model's in the same 8000 steps (INT8
    /// on top: 0.869x to 0.900x); 16 gave 0.910x (0.886x). YOLOv5 heads do not read it.
    pub box_iou: f64,
    /// Weight of YOLOv8's own detection loss (task-aligned assignment, CIoU and DFL on the
    /// boxes, BCE on IoU-aware class targets) on the teacher's detections (score above 0.25,
    /// after NMS), beside the distillation: it ranks each object's best-aligned cells first,
    /// which is what NMS keeps and mAP reads. 0: off. YOLOv5 heads do not read it.
    pub pseudo_labels: f64,
}

#[derive(serde::Deserialize, serde::Serialize, Clone, Copy, Debug, PartialEq, Eq, Default)]
#[serde(rename_all = "lowercase")]
pub enum Train {
    #[default]
    All,
    Estimates,
}

impl Options {
    /// The ranges, checked when the recipe loads.
    pub fn check(&self) -> Result<()> {
        self.schedule.check("")?;
        if self.frames < self.schedule.batch {
            bail!("frames ({}) must be at least batch ({})", self.frames, self.schedule.batch);
        }
        if ![self.box_edges, self.class_foreground, self.v5_box_edges, self.box_iou, self.pseudo_labels].iter().all(|w| *w >= 0.0 && w.is_finite()) {
            bail!("box_edges, class_foreground, v5_box_edges, box_iou and pseudo_labels must be finite and 0 or more");
        }
        Ok(())
    }
}

impl Default for Options {
    fn default() -> Self {
        Options { schedule: Schedule::new(1000, 1e-3, 16), frames: 512, seed: 0, train: Train::All, box_edges: 16.0, class_foreground: 4.0, v5_box_edges: 16.0, box_iou: 64.0, pseudo_labels: 0.0 }
    }
}

pub struct Recover {
    pub options: Options,
}

/// Frames held out from training to judge it (not the worker's: the pass decides with them).
const HELD_OUT: usize = 16;

impl Pass for Recover {
    fn name(&self) -> &'static str {
        "recover"
    }

    fn check(&self) -> Result<()> {
        self.options.check()
    }

    fn needs(&self) -> Vec<super::Capability> {
        vec![super::Capability::Teacher]
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let o = &self.options;
        let Teacher { model: teacher, kept, window, estimates } = cx.teacher.clone().ok_or_else(|| anyhow!("recover distills a pruned or scene-specialized model from the model before: put a prune pass before it in the recipe (or specialize with --scene)"))?;
        // Frames are the teacher's: with a scene ROI the student sees their crop.
        let g = teacher.graph.as_ref().ok_or_else(|| anyhow!("teacher has no graph"))?;
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        let frames = affordable_frames("recover", &graph, &inf, o.frames);
        let (feeds, source) = image_feeds(&graph, &inf, cx.calib.as_deref(), frames + HELD_OUT, o.seed.wrapping_add(17))?;
        if feeds.len() < o.schedule.batch + 2 {
            bail!("recover got {} frames from {source}; it needs at least {}", feeds.len(), o.schedule.batch + 2);
        }
        let held = HELD_OUT.min(feeds.len() / 4);
        let (train, check) = feeds.split_at(feeds.len() - held);
        let image = |f: &Vec<(String, crate::tensor::Tensor)>| f[0].1.clone();
        let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
        let view = SceneView::of_teacher(model, &teacher)?;
        let reference = ReferenceOutputs::new(&teacher, check, threads, view.as_ref())?;
        let before = reference.errors(model)?;
        let mut trained = model.clone();
        let trainable = match o.train {
            Train::All => None,
            Train::Estimates => Some(present(model, &estimates)?),
        };
        let opts = Training { schedule: o.schedule.clone(), seed: o.seed, window, trainable, box_edges: o.box_edges, class_foreground: o.class_foreground, v5_box_edges: o.v5_box_edges, box_iou: o.box_iou, pseudo_labels: o.pseudo_labels };
        let outcome = distill(&mut trained, &teacher, &kept, &train.iter().map(image).collect::<Vec<_>>(), &check.iter().map(image).collect::<Vec<_>>(), &opts)?;
        cx.record_training(&outcome);
        let after = reference.errors(&trained)?;
        // Detections decide where they can be decoded: a pruned head whose class scores all
        // sit near zero is at rel L2 1.0, and a half-recovered one that finds most objects
        // with a few extra boxes can sit above it. A scene's student sees a window of the
        // teacher's frames, so there (and without a head) the worst output group decides.
        // The teacher's detections are decoded once for both scores.
        let agreement = if view.is_none() { DetectionAgreement::of(&teacher, check, threads)? } else { None };
        let judged = agreement.map(|a| Ok::<_, anyhow::Error>((a.score(model)?, a.score(&trained)?))).transpose()?;
        let kept = match judged {
            Some((b, a)) if a != b => a > b,
            _ => worst_rel_l2(&after) < worst_rel_l2(&before),
        };
        if kept {
            *model = trained;
        }
        Ok(serde_json::json!({
            "kept": kept,
            "train": o.train,
            "box_edges": o.box_edges,
            "class_foreground": o.class_foreground,
            "v5_box_edges": o.v5_box_edges,
            "box_iou": o.box_iou,
            "pseudo_labels": o.pseudo_labels,
            "frames": train.len(),
            "held_out_frames": check.len(),
            "calibration": source,
            "output_rel_l2": { "before": by_name(&before), "after": by_name(&after) },
            "detection_agreement": judged.map(|(b, a)| serde_json::json!({"before": b, "after": a})),
            "not_reproducible": outcome.not_reproducible(),
            "training": outcome,
        }))
    }
}

/// The crop's estimates still in `model`: a pass between `crop-roi` and `recover` that rewrote
/// them (pruning cuts the halos' channels too) leaves nothing to train.
fn present(model: &ModelProto, estimates: &[String]) -> Result<Vec<String>> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("the model has no graph"))?;
    let left: Vec<String> = estimates.iter().filter(|e| g.initializer.iter().any(|t| &t.name == *e)).cloned().collect();
    if left.is_empty() {
        bail!("recover's `train: estimates` trains the halos and pool corrections crop-roi fitted, and this model has none: put it right after crop-roi (with a scene roi and `halo` other than zero)");
    }
    Ok(left)
}

/// Trains `student`'s weights towards `teacher` on `frames` (each [1, 1, H, W]), measuring on
/// `held_out`; writes them into `student`.
fn distill(student: &mut ModelProto, teacher: &ModelProto, kept: &HashMap<String, Vec<usize>>, frames: &[Tensor], held_out: &[Tensor], o: &Training) -> Result<Outcome> {
    let heads = head_specs_against(student, kept)?;
    let features = feature_specs(student, kept)?;
    let job = Job { heads, features, extra: serde_json::json!({}), outputs: false, label: "recover" };
    Ok(train(student, teacher, frames, held_out, o, job)?.0)
}
