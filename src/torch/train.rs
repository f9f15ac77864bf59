//! The Rust half of training: a job for the PyTorch worker (`trainer.py`) written to a
//! scratch folder, run through `pyenv::run_worker`, and its trained values taken back. Only
//! initializer values come back: node list, initializer names and shapes are checked against
//! what was sent. Also the op check (`opcheck.py`) and the frames' file format the workers
//! read.

use super::schedule::Schedule;
use crate::onnx::proto::ModelProto;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::ffi::OsStr;
use std::path::Path;

/// One training's settings: the pass's schedule and what it trains towards.
pub struct Training {
    pub schedule: Schedule,
    /// Seed of frame order and augmentation.
    pub seed: u64,
    /// The teacher's frames are full frames; the student sees this window of them.
    pub window: Option<crate::frames::Roi>,
    /// The initializers that train (any float initializer, whatever reads it); None: every
    /// Conv weight and bias.
    pub trainable: Option<Vec<String>>,
    /// Weight of the YOLOv8 box edges' own error beside the DFL distributions' KL (0: the KL
    /// alone); `train` puts it on every box head it is given.
    pub box_edges: f64,
    /// Weight of the YOLOv8 class scores' KL where the teacher sees an object, beside the
    /// plain mean over every cell (0: the mean alone); `train` puts it on every class head.
    pub class_foreground: f64,
    /// Weight of the YOLOv5 box sides' absolute error beside the squared error of its box
    /// terms (0: off); `train` puts it on every YOLOv5 head that carries boxes.
    pub v5_box_edges: f64,
    /// Weight of 1 − IoU between the student's and the teacher's YOLOv8 boxes (each side's
    /// expected distance, the boxes sharing their anchor point) beside the box edges (0:
    /// off); `train` puts it on every box head it is given.
    pub box_iou: f64,
    /// Weight of YOLOv8's own loss on the teacher's detections (`pseudo.py`) beside the
    /// distillation (0: off); heads other than YOLOv8's do not read it.
    pub pseudo_labels: f64,
}

/// What one distillation did, from the worker's own account.
#[derive(serde::Serialize, serde::Deserialize, Debug)]
pub struct Outcome {
    pub held_out_loss_before: f64,
    pub held_out_loss_after: f64,
    pub loss_per_epoch: Vec<f64>,
    pub epochs: usize,
    /// Steps taken, of `steps_planned`; fewer only when the time cap stopped the run.
    pub steps: usize,
    pub steps_planned: usize,
    pub capped: bool,
    pub threads: usize,
    /// Processes that trained together (torchrun's world size).
    #[serde(default = "one")]
    pub ranks: usize,
    pub seconds: f64,
    pub frames_per_second: f64,
    #[serde(default)]
    pub steps_per_second: f64,
    /// On a GPU, the share of time it was busy while training (sampled through NVML).
    #[serde(default)]
    pub gpu_busy_share: Option<f64>,
    /// Frames per step (all ranks together).
    #[serde(default)]
    pub batch: usize,
    /// On one GPU: whether the step was captured as a CUDA graph, or why not.
    #[serde(default)]
    pub cuda_graph: Option<serde_json::Value>,
    /// The crops trained on (`WxH`), or None for whole frames.
    #[serde(default)]
    pub crop: Option<String>,
    /// With `ema`: its decay, the held-out loss of the last step's weights and of the
    /// average, and whether the average was kept.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ema: Option<serde_json::Value>,
    pub device: String,
    pub torch: String,
}

fn one() -> usize {
    1
}

/// What the manifest keeps of one training: which pass trained, where, how far.
#[derive(serde::Serialize, serde::Deserialize, Clone, Debug, PartialEq)]
pub struct Account {
    pub pass: String,
    pub device: String,
    pub threads: usize,
    pub torch: String,
    pub steps: usize,
    pub steps_planned: usize,
    pub capped: bool,
    /// Why a rebuild would not give the same bytes, if it would not ([`Outcome::not_reproducible`]).
    #[serde(skip)]
    pub not_reproducible: Option<String>,
}

impl Outcome {
    /// The account of this training by `pass`.
    pub fn account(&self, pass: &str) -> Account {
        Account {
            pass: pass.to_string(),
            device: self.device.clone(),
            threads: self.threads,
            torch: self.torch.clone(),
            steps: self.steps,
            steps_planned: self.steps_planned,
            capped: self.capped,
            not_reproducible: self.not_reproducible(),
        }
    }

    /// What a report and the manifest say of a run the time cap stopped.
    pub fn cap_note(&self) -> String {
        format!("stopped at {} of {} steps by the time cap; the artifact is not reproducible", self.steps, self.steps_planned)
    }

    /// Why the trained weights would not come out the same on a rebuild, if they would not:
    /// the time cap bit, or the training ran on a GPU (cuDNN picks its kernels by timing
    /// them, runs convolutions in TF32 and sums gradients with atomics: the same job gives
    /// other last bits each time).
    pub fn not_reproducible(&self) -> Option<String> {
        if self.capped {
            return Some(self.cap_note());
        }
        self.device.starts_with("cuda").then(|| format!("trained on {}: GPU kernels do not sum in the same order twice; the artifact is not reproducible byte for byte", self.device))
    }
}

/// What a training run distills beyond the common options.
pub struct Job {
    /// Head convolution values and how to read them (`head_specs`).
    pub heads: Vec<serde_json::Value>,
    /// Intermediate values matched against the teacher's (`feature_specs`).
    pub features: Vec<serde_json::Value>,
    /// Further worker settings (a quantized student's weight range, per-tensor steps).
    pub extra: serde_json::Value,
    /// Whether the worker also returns the trained module's graph outputs on `held_out`.
    pub outputs: bool,
    /// The progress bar's name.
    pub label: &'static str,
}

/// Adds `o`'s terms to the heads that read them: the YOLOv8 box edges and box IoU to its box
/// heads, the class scores' foreground term to its class heads, and the YOLOv5 box sides'
/// term to the YOLOv5 heads that carry boxes.
fn weigh_terms(heads: &mut [serde_json::Value], o: &Training) {
    for h in heads.iter_mut() {
        match h["kind"].as_str() {
            Some("v8box") => {
                h["edge_weight"] = serde_json::json!(o.box_edges);
                if o.box_iou > 0.0 {
                    h["iou_weight"] = serde_json::json!(o.box_iou);
                }
            }
            Some("v8cls") => h["foreground"] = serde_json::json!(o.class_foreground),
            Some("v5" | "v5box") if o.v5_box_edges > 0.0 => h["edge_weight"] = serde_json::json!(o.v5_box_edges),
            _ => {}
        }
    }
}

/// Runs the worker on `student` and `teacher`; writes the trained values into `student` and
/// returns the worker's account and, when asked, its outputs on `held_out` (one tensor per
/// graph output, frames stacked).
pub fn train(student: &mut ModelProto, teacher: &ModelProto, frames: &[Tensor], held_out: &[Tensor], o: &Training, mut job: Job) -> Result<(Outcome, Vec<Tensor>)> {
    weigh_terms(&mut job.heads, o);
    let s = &o.schedule;
    let work = tempfile::tempdir()?;
    let dir = work.path();
    crate::onnx::save(student, &dir.join("student.onnx"))?;
    crate::onnx::save(teacher, &dir.join("teacher.onnx"))?;
    write_frames(frames, &dir.join("frames.npy"))?;
    write_frames(held_out, &dir.join("held_out.npy"))?;
    let crop = crop_plan(student, teacher, frames, o, &job)?;
    let batch = frames_per_step(frames, o);
    let outputs_to = dir.join("outputs");
    std::fs::create_dir(&outputs_to)?;
    let mut config = serde_json::json!({
        "student": dir.join("student.onnx"), "teacher": dir.join("teacher.onnx"), "out": dir.join("trained.onnx"),
        "frames": dir.join("frames.npy"), "held_out": dir.join("held_out.npy"), "heads": job.heads, "features": job.features,
        "window": o.window, "crop": crop, "trainable": o.trainable, "steps": s.steps, "warmup": s.warmup, "minutes": s.minutes, "threads": (s.threads() / s.devices.max(1)).max(1), "lr": s.lr, "batch": batch, "seed": o.seed, "cuda_graph": s.cuda_graph, "ema": s.ema, "pseudo_labels": o.pseudo_labels,
        "device": if s.device.is_empty() { serde_json::Value::Null } else { s.device.clone().into() },
        "outputs_to": if job.outputs { serde_json::json!(outputs_to) } else { serde_json::Value::Null },
    });
    if let (Some(c), Some(extra)) = (config.as_object_mut(), job.extra.as_object()) {
        c.extend(extra.clone());
    }
    std::fs::write(dir.join("config.json"), serde_json::to_vec(&config)?)?;
    let pb = ProgressBar::new(1);
    pb.set_length(s.steps as u64);
    pb.set_style(ProgressStyle::with_template(&format!("{} [{{bar:30}}] {{pos}}/{{len}} steps, {{msg}} ({{elapsed}}, {{eta}} left)", job.label)).expect("valid template").progress_chars("=> "));
    let config_path = dir.join("config.json");
    let args = [OsStr::new("train"), config_path.as_os_str()];
    let done = super::run(dir, "trainer.py", &args, s.devices, |event| match event["event"].as_str() {
        Some("start") => pb.set_message(format!("on {}", event["device"].as_str().unwrap_or("?"))),
        Some("step") | Some("epoch") => {
            pb.set_length(event["steps"].as_u64().unwrap_or(1));
            pb.set_position(event["step"].as_u64().unwrap_or(0));
            pb.set_message(format!("loss {:.4}", event["loss"].as_f64().unwrap_or(f64::NAN)));
        }
        _ => {}
    });
    pb.finish_and_clear();
    let outcome: Outcome = serde_json::from_value(done?)?;
    if outcome.capped {
        crate::warn::warn(format!("{}: {}", job.label, outcome.cap_note()));
    }
    let trained = crate::onnx::load(&dir.join("trained.onnx"))?.model;
    take_weights(student, &trained)?;
    let n_outputs = student.graph.as_ref().map_or(0, |g| g.output.len());
    let outputs = if job.outputs { (0..n_outputs).map(|k| read_tensor(&outputs_to.join(format!("out{k}.npy")))).collect::<Result<_>>()? } else { Vec::new() };
    Ok((outcome, outputs))
}

/// Frames a step trains on: `crop: auto` counts the batch in frames of 256x192 (a scene's
/// student sees its window, and its batch stays as written).
fn frames_per_step(frames: &[Tensor], o: &Training) -> usize {
    let s = &o.schedule;
    match frames.first().map(|f| f.shape.as_slice()) {
        Some([_, _, h, w]) if o.window.is_none() => super::crops::frames_per_step(s.crop, s.batch, (*h, *w), s.devices),
        _ => s.batch,
    }
}

/// How the job crops its frames (`crops`), if it does: a scene's window already crops the
/// student, so `auto` leaves it whole and a crop size is refused beside it.
fn crop_plan(student: &ModelProto, teacher: &ModelProto, frames: &[Tensor], o: &Training, job: &Job) -> Result<Option<super::crops::Plan>> {
    let Some(dims) = frames.first().map(|f| &f.shape) else { return Ok(None) };
    if dims.len() != 4 {
        return Ok(None);
    }
    if o.window.is_some() {
        if let super::crops::Crop::Size(..) = o.schedule.crop {
            bail!("{}: crop {} cannot combine with a scene's roi (the student already sees a window); set crop: auto or none", job.label, o.schedule.crop);
        }
        return Ok(None);
    }
    let names = |key: &str| -> Vec<String> {
        job.heads.iter().map(|h| h.get(key).and_then(|v| v.as_str()).or(h["value"].as_str()).unwrap_or_default().to_string())
            .chain(job.features.iter().filter_map(|f| f["value"].as_str().map(String::from))).collect()
    };
    super::crops::plan(o.schedule.crop, (student, &names("student_value")), (teacher, &names("value")), (dims[2], dims[3])).map_err(|e| anyhow!("{}: {e}", job.label))
}

fn read_tensor(path: &Path) -> Result<Tensor> {
    let a = crate::optics::npy::read(path)?;
    Ok(Tensor::f32(a.shape, a.data))
}

/// What `check_ops` measured: per op type, the worst difference from ONNX Runtime on each
/// value's scale (floored at 1); per form the interpreter trains a Conv in other than plain
/// torch (`columns`, `depthwise`), the worst difference of its gradients from torch's own.
#[derive(serde::Deserialize, Debug)]
pub struct OpCheck {
    pub ops: std::collections::BTreeMap<String, f64>,
    pub gradients: std::collections::BTreeMap<String, f64>,
}

/// Runs every node of `model` in the worker's torch interpreter and in ONNX Runtime on
/// `frames`, and the interpreter's own Conv gradients against torch's.
pub fn check_ops(model: &ModelProto, frames: &[Tensor]) -> Result<OpCheck> {
    let work = tempfile::tempdir()?;
    let dir = work.path();
    crate::onnx::save(model, &dir.join("model.onnx"))?;
    write_frames(frames, &dir.join("frames.npy"))?;
    let (model, frames) = (dir.join("model.onnx"), dir.join("frames.npy"));
    let done = super::run(dir, "opcheck.py", &[model.as_os_str(), frames.as_os_str()], 1, |_| {}).context("the op check")?;
    serde_json::from_value(done).map_err(Into::into)
}

/// Copies `trained`'s initializer values into `model`, refusing anything but new values.
fn take_weights(model: &mut ModelProto, trained: &ModelProto) -> Result<()> {
    let (g, t) = (model.graph.as_mut().expect("checked"), trained.graph.as_ref().ok_or_else(|| anyhow!("trained model has no graph"))?);
    if g.node != t.node {
        bail!("the recovery worker changed the graph's nodes; this is a bug, please report it");
    }
    if g.initializer.len() != t.initializer.len() || g.initializer.iter().zip(&t.initializer).any(|(a, b)| a.name != b.name || a.dims != b.dims || a.data_type != b.data_type) {
        bail!("the recovery worker changed the initializers' names, shapes or types; this is a bug, please report it");
    }
    for (a, b) in g.initializer.iter_mut().zip(&t.initializer) {
        let value = crate::onnx::tensor_proto::to_tensor(b)?;
        if value.as_f32().is_some_and(|v| v.iter().any(|x| !x.is_finite())) {
            bail!("recovery diverged: '{}' has non-finite values; lower the recover pass's lr", a.name);
        }
        *a = b.clone();
    }
    Ok(())
}

/// Frames (each [1, C, H, W]) as one [N, C, H, W] .npy file, for the torch workers.
pub fn write_frames(frames: &[Tensor], path: &Path) -> Result<()> {
    let first = frames.first().ok_or_else(|| anyhow!("recover needs frames"))?;
    let mut shape = first.shape.clone();
    shape[0] = frames.len();
    let mut data = Vec::with_capacity(first.len() * frames.len());
    for f in frames {
        data.extend_from_slice(f.as_f32().ok_or_else(|| anyhow!("frames are float"))?);
    }
    std::fs::write(path, crate::optics::npy::to_bytes(&shape, &data))?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::{weigh_terms, Outcome, Training};
    use crate::torch::schedule::Schedule;

    #[test]
    fn each_head_kind_gets_its_own_terms() {
        let terms = |v5_box_edges, box_iou| Training { schedule: Schedule::new(1, 1e-3, 1), seed: 0, window: None, trainable: None, box_edges: 4.0, class_foreground: 2.0, v5_box_edges, box_iou, pseudo_labels: 0.0 };
        let mut heads = vec![serde_json::json!({"kind": "v8box"}), serde_json::json!({"kind": "v8cls"}), serde_json::json!({"kind": "v5"}), serde_json::json!({"kind": "v5scores"})];
        weigh_terms(&mut heads, &terms(0.0, 0.0));
        assert_eq!(heads[0]["edge_weight"], 4.0);
        assert_eq!(heads[1]["foreground"], 2.0);
        assert!(heads[0].get("foreground").is_none() && heads[1].get("edge_weight").is_none());
        assert!(heads.iter().all(|h| h.get("iou_weight").is_none()));
        assert!(heads[2].get("edge_weight").is_none() && heads[2].get("foreground").is_none());
        weigh_terms(&mut heads, &terms(8.0, 3.0));
        assert_eq!(heads[2]["edge_weight"], 8.0);
        assert_eq!(heads[0]["iou_weight"], 3.0);
        assert!(heads[3].get("edge_weight").is_none() && heads[2].get("iou_weight").is_none());
    }

    /// A GPU's training, or one the time cap stopped, is marked not reproducible; a whole CPU
    /// training is not (its bytes are checked by the rebuild tests).
    #[test]
    fn a_gpu_or_capped_training_is_marked_not_reproducible() {
        let outcome = |device: &str, capped: bool| -> Outcome {
            serde_json::from_value(serde_json::json!({"held_out_loss_before": 1.0, "held_out_loss_after": 0.5, "loss_per_epoch": [], "epochs": 1, "steps": 10, "steps_planned": 20,
                "capped": capped, "threads": 2, "seconds": 1.0, "frames_per_second": 1.0, "device": device, "torch": "2.4"})).unwrap()
        };
        assert_eq!(outcome("cpu", false).not_reproducible(), None);
        assert!(outcome("cpu", true).not_reproducible().unwrap().contains("time cap"));
        assert!(outcome("cuda:0", false).not_reproducible().unwrap().contains("trained on cuda:0"));
    }
}
