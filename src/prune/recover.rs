//! Recovery by distillation: the pruned model trained to match the unpruned one's head
//! convolutions and their input features, in a PyTorch worker (`src/torch/trainer.py`, run by the cache's torch Python).
//! Only initializer values come back: node list, initializer names and shapes are checked
//! against what was sent.

use crate::analysis::channels::detector_convolutions;
use crate::analysis::head::{self, HeadKind};
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Context, Result};
use indicatif::{ProgressBar, ProgressStyle};
use std::collections::HashMap;
use std::ffi::OsStr;
use std::path::Path;


pub struct Options {
    /// Optimizer steps: the schedule (warm-up, cosine decay) follows them alone.
    pub steps: usize,
    /// Linear warm-up steps at the start of the schedule.
    pub warmup: usize,
    /// A cap on the training's wall time; when it bites the run stops early and says so.
    pub minutes: Option<f64>,
    /// Torch's (and the CPU teacher's) threads: fixed, so that sums come out the same.
    pub threads: usize,
    pub lr: f64,
    pub batch: usize,
    pub seed: u64,
    /// `cuda`, `cpu`, or empty for CUDA when torch sees a GPU.
    pub device: String,
    /// Ranks of one torch.distributed job (torchrun); 1 trains in one process.
    pub devices: usize,
    /// On one GPU, the training step captured once as a CUDA graph and replayed.
    pub cuda_graph: bool,
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
    pub device: String,
    pub torch: String,
}

fn one() -> usize {
    1
}

/// Checks the schedule every training pass shares; `within` prefixes the message where the
/// schedule is a sub-option (`qat: `), the pass name being the error's context.
pub fn check_schedule(within: &str, steps: usize, minutes: Option<f64>, lr: f64, batch: usize) -> Result<()> {
    if steps == 0 || batch == 0 {
        bail!("{within}steps and batch must be at least 1");
    }
    // `!(x > 0)` refuses NaN too.
    if !(lr > 0.0 && lr.is_finite()) {
        bail!("{within}lr must be a positive number");
    }
    if minutes.is_some_and(|m| !(m > 0.0 && m.is_finite())) {
        bail!("{within}minutes (a time cap) must be a positive number");
    }
    Ok(())
}

/// A training thread count: 0 is every core of this machine, resolved once so that the
/// manifest records the count the weights were trained with.
/// Checks a `devices` option: at least 1, at most 64, and `batch` an equal share for each.
pub fn check_devices(within: &str, devices: usize, batch: usize) -> Result<()> {
    if !(1..=64).contains(&devices) {
        bail!("{within}devices must be 1 to 64 (got {devices})");
    }
    if batch % devices != 0 {
        bail!("{within}batch ({batch}) must divide among the devices ({devices}): each takes an equal share of every batch");
    }
    Ok(())
}

pub fn resolve_threads(threads: usize) -> usize {
    if threads > 0 { threads } else { std::thread::available_parallelism().map_or(1, |n| n.get()) }
}

impl Outcome {
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

/// The head convolutions to distil and how to read their channels, for the worker.
pub fn head_specs(model: &ModelProto) -> Result<Vec<serde_json::Value>> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
    let head = head::detect(&graph, &inf, &outputs);
    let nc = head.classes.ok_or_else(|| anyhow!("recover needs a YOLOv5 or YOLOv8 head with a known class count"))?;
    let mut specs = Vec::new();
    for i in detector_convolutions(&graph) {
        let n = graph.node(i);
        let channels = n.input.get(1).and_then(|w| graph.initializers.get(w.as_str())).and_then(|w| w.dims.first()).copied().unwrap_or(0) as usize;
        let value = n.output[0].clone();
        let spec = match head.kind {
            HeadKind::Yolov5Anchor if channels % (5 + nc) == 0 => serde_json::json!({"value": value, "kind": "v5", "anchors": channels / (5 + nc), "outputs": 5 + nc}),
            HeadKind::Yolov8Dfl if Some(channels) == head.reg_max.map(|r| 4 * r) => serde_json::json!({"value": value, "kind": "v8box", "reg_max": head.reg_max}),
            HeadKind::Yolov8Dfl if channels == nc => serde_json::json!({"value": value, "kind": "v8cls"}),
            _ => bail!("head convolution '{}' ({channels} channels) does not fit a {:?} head with {nc} classes; recover cannot read it", n.name, head.kind),
        };
        specs.push(spec);
    }
    if specs.is_empty() {
        bail!("no head convolutions found; recover needs a detector ending in convolutions");
    }
    Ok(specs)
}

/// `head_specs` of a student distilled from a teacher it was cut from: each head
/// convolution a scene dropped rows from reads the teacher's kept rows.
pub fn head_specs_against(student: &ModelProto, kept: &HashMap<String, Vec<usize>>) -> Result<Vec<serde_json::Value>> {
    let mut heads = head_specs(student)?;
    for h in &mut heads {
        if let Some(k) = h["value"].as_str().and_then(|v| kept.get(v)) {
            h["keep"] = serde_json::json!(k);
        }
    }
    Ok(heads)
}

/// The head values of a model from rknn-legalize (per-stride boxes and scores), for the
/// worker: each output's logits (a Sigmoid's input), YOLOv8's box distributions as they are.
/// `student_value` names the student's copy of a value where it differs (a quantized model's
/// dequantized value).
pub fn split_head_specs(model: &ModelProto, student_value: &std::collections::BTreeMap<String, String>) -> Result<Vec<serde_json::Value>> {
    use crate::detect::split_head::HeadLayout;
    let layout = HeadLayout::from_model(model)?;
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let logits = |out: &str| -> String {
        match g.node.iter().find(|n| n.output.iter().any(|o| o == out)) {
            Some(n) if n.op_type == "Sigmoid" => n.input[0].clone(),
            _ => out.to_string(),
        }
    };
    let spec = |value: String, rest: serde_json::Value| {
        let mut s = serde_json::json!({"value": value, "student_value": student_value.get(&value)});
        if let (Some(a), Some(b)) = (s.as_object_mut(), rest.as_object()) {
            a.extend(b.clone());
        }
        s
    };
    let nc = layout.classes;
    let mut specs = Vec::new();
    for l in &layout.levels {
        match layout.kind {
            HeadKind::Yolov5Anchor => {
                let na = l.anchors.len();
                specs.push(spec(logits(&l.boxes), serde_json::json!({"kind": "v5box", "anchors": na})));
                specs.push(spec(logits(&l.scores), serde_json::json!({"kind": "v5scores", "anchors": na, "outputs": 1 + nc})));
            }
            HeadKind::Yolov8Dfl => {
                specs.push(spec(l.boxes.clone(), serde_json::json!({"kind": "v8box", "reg_max": layout.reg_max})));
                specs.push(spec(logits(&l.scores), serde_json::json!({"kind": "v8cls"})));
            }
            ref other => bail!("a {other:?} head cannot be distilled"),
        }
    }
    Ok(specs)
}

/// The head convolutions' inputs and the neck outputs their branches start from, matched
/// channel by channel: a pruned value's kept positions index the teacher's channels (a dense
/// signal where the logits are sparse).
pub fn feature_specs(model: &ModelProto, kept: &HashMap<String, Vec<usize>>) -> Result<Vec<serde_json::Value>> {
    let graph = Graph::build(model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?)?;
    let inputs: Vec<String> = detector_convolutions(&graph).into_iter().map(|i| graph.node(i).input[0].clone()).collect();
    let mut values: Vec<String> = inputs.iter().filter_map(|v| branch_root(&graph, v)).chain(inputs.iter().cloned()).collect();
    values.sort();
    values.dedup();
    Ok(values.into_iter().map(|v| serde_json::json!({ "value": v, "keep": kept.get(&v) })).collect())
}

/// Where the head branch ending in value `v` starts: up through the branch's own
/// convolutions (each value read by one convolution, SiLU pairs looked through) to the first
/// value several convolutions read, the neck output a YOLOv8 head's box and class branches
/// share. None when `v` is that already (a YOLOv5 head reads the neck directly).
fn branch_root(g: &Graph, v: &str) -> Option<String> {
    let conv_readers = |v: &str| g.consumers_of(v).iter().filter(|&&c| g.node(c).op_type == "Conv").count();
    let mut v = v.to_string();
    // Heads are a few convolutions deep: a longer walk has left the head.
    for _ in 0..4 {
        if conv_readers(&v) != 1 {
            return None;
        }
        let p = g.producer_of(&v)?;
        let x = if p.op_type == "Mul" { p.input[0].as_str() } else { v.as_str() };
        let conv = g.producer_of(x).filter(|n| n.op_type == "Conv")?;
        let u = conv.input[0].clone();
        if conv_readers(&u) > 1 {
            return Some(u);
        }
        v = u;
    }
    None
}

/// Trains `student`'s weights towards `teacher` on `frames` (each [1, 1, H, W]), measuring on
/// `held_out`; writes them into `student`.
pub fn distill(student: &mut ModelProto, teacher: &ModelProto, kept: &HashMap<String, Vec<usize>>, frames: &[Tensor], held_out: &[Tensor], o: &Options) -> Result<Outcome> {
    let heads = head_specs_against(student, kept)?;
    let features = feature_specs(student, kept)?;
    let job = Job { heads, features, extra: serde_json::json!({}), outputs: false, label: "recover" };
    Ok(train(student, teacher, frames, held_out, o, job)?.0)
}

/// What a training run distills beyond the common options.
pub(crate) struct Job {
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

/// Adds the YOLOv8 box edges' own term, at `edges`, to its box heads, and the class scores'
/// foreground term, at `foreground`, to its class heads.
fn weigh_terms(heads: &mut [serde_json::Value], edges: f64, foreground: f64) {
    for h in heads.iter_mut() {
        match h["kind"].as_str() {
            Some("v8box") => h["edge_weight"] = serde_json::json!(edges),
            Some("v8cls") => h["foreground"] = serde_json::json!(foreground),
            _ => {}
        }
    }
}

/// Runs the worker on `student` and `teacher`; writes the trained values into `student` and
/// returns the worker's account and, when asked, its outputs on `held_out` (one tensor per
/// graph output, frames stacked).
pub(crate) fn train(student: &mut ModelProto, teacher: &ModelProto, frames: &[Tensor], held_out: &[Tensor], o: &Options, mut job: Job) -> Result<(Outcome, Vec<Tensor>)> {
    weigh_terms(&mut job.heads, o.box_edges, o.class_foreground);
    let work = tempfile::tempdir()?;
    let dir = work.path();
    crate::onnx::save(student, &dir.join("student.onnx"))?;
    crate::onnx::save(teacher, &dir.join("teacher.onnx"))?;
    write_frames(frames, &dir.join("frames.npy"))?;
    write_frames(held_out, &dir.join("held_out.npy"))?;
    let outputs_to = dir.join("outputs");
    std::fs::create_dir(&outputs_to)?;
    let mut config = serde_json::json!({
        "student": dir.join("student.onnx"), "teacher": dir.join("teacher.onnx"), "out": dir.join("trained.onnx"),
        "frames": dir.join("frames.npy"), "held_out": dir.join("held_out.npy"), "heads": job.heads, "features": job.features,
        "window": o.window, "trainable": o.trainable, "steps": o.steps, "warmup": o.warmup, "minutes": o.minutes, "threads": (o.threads / o.devices.max(1)).max(1), "lr": o.lr, "batch": o.batch, "seed": o.seed, "cuda_graph": o.cuda_graph,
        "device": if o.device.is_empty() { serde_json::Value::Null } else { o.device.clone().into() },
        "outputs_to": if job.outputs { serde_json::json!(outputs_to) } else { serde_json::Value::Null },
    });
    if let (Some(c), Some(extra)) = (config.as_object_mut(), job.extra.as_object()) {
        c.extend(extra.clone());
    }
    std::fs::write(dir.join("config.json"), serde_json::to_vec(&config)?)?;
    let pb = ProgressBar::new(1);
    pb.set_length(o.steps as u64);
    pb.set_style(ProgressStyle::with_template(&format!("{} [{{bar:30}}] {{pos}}/{{len}} steps, {{msg}} ({{elapsed}}, {{eta}} left)", job.label)).expect("valid template").progress_chars("=> "));
    let config_path = dir.join("config.json");
    let args = [OsStr::new("train"), config_path.as_os_str()];
    let done = crate::torch::run(dir, "trainer.py", &args, o.devices, |event| match event["event"].as_str() {
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
    let done = crate::torch::run(dir, "opcheck.py", &[model.as_os_str(), frames.as_os_str()], 1, |_| {}).context("the op check")?;
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
pub(crate) fn write_frames(frames: &[Tensor], path: &Path) -> Result<()> {
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
    use super::{weigh_terms, Outcome};

    #[test]
    fn each_yolov8_head_gets_its_own_term() {
        let mut heads = vec![serde_json::json!({"kind": "v8box"}), serde_json::json!({"kind": "v8cls"}), serde_json::json!({"kind": "v5"})];
        weigh_terms(&mut heads, 4.0, 2.0);
        assert_eq!(heads[0]["edge_weight"], 4.0);
        assert_eq!(heads[1]["foreground"], 2.0);
        assert!(heads[0].get("foreground").is_none() && heads[1].get("edge_weight").is_none());
        assert!(heads[2].get("edge_weight").is_none() && heads[2].get("foreground").is_none());
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
