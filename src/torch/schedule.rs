//! The training schedule every training pass shares (`recover`, `quantize`'s `qat`,
//! `rknn-qat`): declared once, flattened into each pass's options (recipes keep flat keys),
//! checked once. Each pass gives its own defaults ([`Schedule::new`]).

use anyhow::{bail, Result};

#[derive(serde::Serialize, serde::Deserialize, Clone, Debug, PartialEq)]
pub struct Schedule {
    /// Optimizer steps of batch `batch`: the schedule (warm-up, cosine decay) follows them
    /// alone, whatever the machine's speed.
    pub steps: usize,
    /// Steps of linear warm-up at the start.
    pub warmup: usize,
    /// A cap on the training's wall time (none by default). When it bites, training stops
    /// early, the report and stderr say so, and the artifact is marked not reproducible.
    pub minutes: Option<f64>,
    /// Training threads (torch and the CPU teacher), fixed so that sums come out the same;
    /// 0: every core of the compiling machine, recorded in the manifest.
    pub threads: usize,
    /// The step at the top of the schedule: Adam's learning rate for `recover`; for the
    /// quantization-aware passes a fraction of each tensor's largest magnitude (1e-4 moves a
    /// 7-bit weight about 0.006 of a grid step per iteration, so a few hundred steps can move
    /// it one or two steps and no further).
    pub lr: f64,
    /// Frames per optimizer step.
    pub batch: usize,
    /// `cuda` or `cpu`; empty: CUDA when torch sees a GPU.
    pub device: String,
    /// Processes that train together (torchrun, DistributedDataParallel: NCCL on GPUs, gloo
    /// on the CPU). Each takes an equal share of every batch and the loss is normalized over
    /// the whole batch, so the weights are one process's up to float summation order; on the
    /// CPU they share `threads`. `batch` must divide among them.
    pub devices: usize,
    /// On one GPU, capture the training step once as a CUDA graph and replay it: one launch
    /// a step instead of about a thousand from Python (on an H200 the pruned width-0.25 v5
    /// at batch 32 trained at 2719 frames/s with the GPU 95% busy, against 855 frames/s and
    /// 32% eagerly). `false`: each step eagerly. Where capture fails, training goes on
    /// eagerly and the report says why.
    pub cuda_graph: bool,
    /// What a step sees: `auto`, whole frames with `batch` counted in frames of 256x192
    /// (2 a step at 640x480 for a batch of 8: about the same pixels); `none`, whole frames,
    /// `batch` of them; `WxH`, random crops of that size, `batch` of them (a 640x480 model
    /// then trains at a 256x192 step's cost, the frame-shaped constants cut with each
    /// window, but on a crop it sees less context than on the camera's frames). Held-out
    /// frames are judged whole.
    pub crop: super::crops::Crop,
    /// Decay of an exponential moving average of the weights (0: none). The average, ramped
    /// in over the first steps, replaces the last step's weights where it is closer to the
    /// teacher on the held-out frames; the report gives both losses.
    pub ema: f64,
}

impl Schedule {
    /// A pass's defaults: `steps` of `batch` at `lr`, no warm-up or time cap, every core, one
    /// process, CUDA (captured) when torch sees a GPU.
    pub fn new(steps: usize, lr: f64, batch: usize) -> Schedule {
        Schedule { steps, warmup: 0, minutes: None, threads: 0, lr, batch, device: String::new(), devices: 1, cuda_graph: true, crop: super::crops::Crop::Auto, ema: 0.0 }
    }

    /// The ranges, checked when the recipe loads; `within` prefixes the message where the
    /// schedule is a sub-option (`qat: `), the pass name being the error's context.
    pub fn check(&self, within: &str) -> Result<()> {
        if self.steps == 0 || self.batch == 0 {
            bail!("{within}steps and batch must be at least 1");
        }
        if self.warmup >= self.steps {
            bail!("{within}warmup ({}) must be fewer than steps ({})", self.warmup, self.steps);
        }
        // `!(x > 0)` refuses NaN too.
        if !(self.lr > 0.0 && self.lr.is_finite()) {
            bail!("{within}lr must be a positive number");
        }
        if self.minutes.is_some_and(|m| !(m > 0.0 && m.is_finite())) {
            bail!("{within}minutes (a time cap) must be a positive number");
        }
        if !(0.0..1.0).contains(&self.ema) {
            bail!("{within}ema (the average's decay) must be at least 0 and below 1 (got {})", self.ema);
        }
        if !(1..=64).contains(&self.devices) {
            bail!("{within}devices must be 1 to 64 (got {})", self.devices);
        }
        if !self.batch.is_multiple_of(self.devices) {
            bail!("{within}batch ({}) must divide among the devices ({}): each takes an equal share of every batch", self.batch, self.devices);
        }
        Ok(())
    }

    /// The thread count to train with: 0 is every core of this machine (its share of them when
    /// workers run side by side: [`crate::pyenv::worker_share`]), resolved once so that the
    /// manifest records the count the weights were trained with.
    pub fn threads(&self) -> usize {
        if self.threads > 0 { self.threads } else { crate::pyenv::worker_share() }
    }
}
