//! What every pass is: the [`Pass`] contract, the context passes share, and what they hand
//! on to later passes. The pipeline (recipes, the runner) sits above and calls it.

use crate::onnx::proto::ModelProto;
use crate::frames::Roi;
use anyhow::Result;
use serde::Serialize;
use std::collections::HashMap;
use std::path::PathBuf;

/// What passes share: what the command line gave, what earlier passes hand on, warnings.
#[derive(Default, Clone, Debug)]
pub struct PassContext {
    /// Camera blur map (`--psf`).
    pub psf: Option<PathBuf>,
    /// Calibration frames (`--calib`).
    pub calib: Option<PathBuf>,
    /// Outputs `strip-recon` keeps (`--keep-outputs`), overriding recognition.
    pub keep_outputs: Option<Vec<String>>,
    /// What the deployment needs (`--scene`): read by the scene passes.
    pub scene: Option<crate::scene::Scene>,
    /// The model before the first structural change: `prune` or a scene pass leaves it here
    /// ([`PassContext::record_cut`], [`PassContext::record_window`]; a later cut composes
    /// with it), `recover` and QAT distill from it.
    pub teacher: Option<Teacher>,
    /// Warnings of the passes run so far, each as "pass: what", in order.
    pub warnings: Vec<String>,
    /// The pass running now (the runner sets it), which names its warnings.
    pub pass: &'static str,
    /// The trainings of the passes run so far ([`PassContext::record_training`]), for the
    /// manifest and the reproducibility verdict.
    pub trainings: Vec<crate::torch::train::Account>,
}

impl PassContext {
    /// A warning of the running pass: printed on stderr now (a user watching a long compile
    /// sees it) and kept for the report.
    pub fn warn(&mut self, msg: impl Into<String>) {
        let line = format!("{}: {}", self.pass, msg.into());
        if !self.warnings.contains(&line) {
            eprintln!("warning: {line}");
            self.warnings.push(line);
        }
    }

    /// Records a training of the running pass.
    pub fn record_training(&mut self, outcome: &crate::torch::train::Outcome) {
        self.trainings.push(outcome.account(self.pass));
    }

    /// Records a channel (or class-row) cut: `kept` indexes the cut model's values. The model
    /// before it becomes the teacher, unless an earlier cut left one: the new cut then composes
    /// with it, and recovery distills through both.
    pub fn record_cut(&mut self, before: impl FnOnce() -> ModelProto, kept: &HashMap<String, Vec<usize>>) {
        match &mut self.teacher {
            Some(t) => t.compose(kept),
            None => self.teacher = Some(Teacher { model: before(), kept: kept.clone(), window: None, estimates: Vec::new() }),
        }
    }

    /// Records a crop to `window` of the teacher's frame, with the initializers the crop fitted.
    pub fn record_window(&mut self, before: impl FnOnce() -> ModelProto, window: Roi, estimates: Vec<String>) {
        match &mut self.teacher {
            Some(t) => (t.window, t.estimates) = (Some(window), estimates),
            None => self.teacher = Some(Teacher { model: before(), kept: HashMap::new(), window: Some(window), estimates }),
        }
    }
}

/// A model before pruning or scene specialization and, for every value that lost channels,
/// the positions it kept; with a scene ROI, the window of the teacher's frame the student sees.
#[derive(Clone, Debug)]
pub struct Teacher {
    pub model: ModelProto,
    pub kept: HashMap<String, Vec<usize>>,
    pub window: Option<Roi>,
    /// The initializers `crop-roi` fitted (halos, pool corrections): what `recover` trains with
    /// `train: estimates`.
    pub estimates: Vec<String>,
}

impl Teacher {
    /// Records a further channel cut: `kept` indexes the current model's channels, which
    /// index the teacher's through the earlier cut.
    fn compose(&mut self, kept: &HashMap<String, Vec<usize>>) {
        for (v, ks) in kept {
            let through = match self.kept.get(v) {
                Some(earlier) => ks.iter().map(|&k| earlier[k]).collect(),
                None => ks.clone(),
            };
            self.kept.insert(v.clone(), through);
        }
    }
}

/// A lossy pass's result past its hard limit: the artifact would be broken, not merely less
/// accurate. The command exits 1 (a quality failure, not bad input) and writes no artifact.
#[derive(Debug)]
pub struct QualityFailure(pub String);

impl std::fmt::Display for QualityFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for QualityFailure {}

/// Whether `e` is, or was caused by, a [`QualityFailure`].
pub fn is_quality_failure(e: &anyhow::Error) -> bool {
    e.chain().any(|c| c.is::<QualityFailure>())
}

/// What a pass needs from the passes before it (or the input model), or provides to those after.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Capability {
    /// The model before a structural change (`prune`, or a scene pass), to distill from.
    Teacher,
    /// A detection head split per stride (`rknn-legalize`), or an input model that has one.
    SplitHead,
}

impl Capability {
    /// What a recipe does to provide it, for the error that names a missing one.
    pub fn remedy(self) -> &'static str {
        match self {
            Capability::Teacher => "put prune (or a scene pass, through --scene) before it",
            Capability::SplitHead => "put rknn-legalize before it",
        }
    }
}

pub trait Pass {
    fn name(&self) -> &'static str;
    /// The options' ranges, checked when the recipe loads, before any pass runs.
    fn check(&self) -> Result<()> {
        Ok(())
    }
    /// What must come before it (from an earlier pass, or the input model).
    fn needs(&self) -> Vec<Capability> {
        Vec::new()
    }
    fn provides(&self) -> Vec<Capability> {
        Vec::new()
    }
    /// Whether the pass takes `narrow-convs-nchw`'s 3-D convolutions as they are; for every
    /// other pass the runner lowers them back to 2-D first.
    fn takes_lifted_convs(&self) -> bool {
        false
    }
    /// Whether the pass takes `space-to-depth`'s blocks as they are; for every other pass the
    /// runner lowers them back first.
    fn takes_space_to_depth(&self) -> bool {
        false
    }
    /// Checks what the pass will need of the input model and the command line (`--psf`),
    /// before any pass runs.
    fn preflight(&self, _input: &ModelProto, _cx: &PassContext) -> Result<()> {
        Ok(())
    }
    /// Rewrites `model`; returns the pass's own report. What it hands to later passes (a
    /// teacher) and its warnings go through `cx`.
    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value>;
}
