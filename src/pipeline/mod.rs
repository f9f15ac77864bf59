//! Pass pipelines: YAML recipes naming passes and their options, run in order.
//!
//! A pass is a unit with a contract: it takes a model, rewrites it, and reports what it did
//! (`serde_json::Value`, pass-specific). The runner adds what every pass report carries:
//! time taken and node/parameter/MAC counts before and after.

pub mod recipe;

use crate::inspect::inspect;
use crate::onnx::proto::ModelProto;
use anyhow::{Context, Result};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

pub use recipe::{PassSpec, Recipe};

/// What passes may need from the command line.
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
    /// The model before the last structural change: `prune` leaves the unpruned model here,
    /// `recover` distills the pruned one from it.
    pub teacher: std::cell::RefCell<Option<Teacher>>,
}

/// A model before pruning or scene specialization and, for every value that lost channels,
/// the positions it kept; with a scene ROI, the window of the teacher's frame the student sees.
#[derive(Clone, Debug)]
pub struct Teacher {
    pub model: ModelProto,
    pub kept: std::collections::HashMap<String, Vec<usize>>,
    pub window: Option<crate::scene::Roi>,
    /// The initializers `crop-roi` fitted (halos, pool corrections): what `recover` trains with
    /// `train: estimates`.
    pub estimates: Vec<String>,
}

impl Teacher {
    /// Records a further channel cut: `kept` indexes the current model's channels, which
    /// index the teacher's through the earlier cut.
    pub fn compose(&mut self, kept: &std::collections::HashMap<String, Vec<usize>>) {
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
    fn remedy(self) -> &'static str {
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
    /// Checks what the pass will need of the input model and the command line (`--psf`),
    /// before any pass runs.
    fn preflight(&self, _input: &ModelProto, _cx: &PassContext) -> Result<()> {
        Ok(())
    }
    /// Rewrites `model`; returns the pass's own report.
    fn run(&self, model: &mut ModelProto, cx: &PassContext) -> Result<serde_json::Value>;
}

pub fn build_pass(spec: &PassSpec) -> Result<Box<dyn Pass>> {
    let built = crate::passes::build(spec)?;
    built.pass.check()?;
    Ok(built.pass)
}

/// `recipe` with every pass's options resolved (defaults filled in): what the manifest
/// records, and what a rebuild runs.
pub fn resolve(recipe: &Recipe) -> Result<Recipe> {
    let mut out = recipe.clone();
    for p in &mut out.passes {
        p.options = crate::passes::build(p).with_context(|| format!("pass {}", p.name))?.options;
    }
    Ok(out)
}

/// Checks a whole recipe before any pass runs, in well under a second: every pass's options
/// and ranges, the order (each need met by an earlier pass or by the input model), and what
/// the command line must supply (`--calib` with frames, `--psf` where a pass needs it). The
/// error names the recipe's line.
pub fn check(recipe: &Recipe, input: &ModelProto, cx: &PassContext) -> Result<()> {
    if let Some(dir) = &cx.calib {
        let n = crate::frames::count(dir).with_context(|| format!("--calib {}", dir.display()))?;
        if n == 0 {
            anyhow::bail!("--calib {}: no frames (PNG/TIFF 8/16-bit grayscale or .npy)", dir.display());
        }
    }
    if let Some(psf) = &cx.psf {
        if !psf.is_file() {
            anyhow::bail!("--psf {}: no such file", psf.display());
        }
    }
    let passes: Vec<Box<dyn Pass>> = recipe.passes.iter().map(|s| build_pass(s).with_context(|| s.at())).collect::<Result<_>>()?;
    let mut have: Vec<Capability> = Vec::new();
    if crate::detect::split_head::HeadLayout::from_model(input).is_ok() {
        have.push(Capability::SplitHead);
    }
    for (pass, spec) in passes.iter().zip(&recipe.passes) {
        if let Some(missing) = pass.needs().into_iter().find(|n| !have.contains(n)) {
            anyhow::bail!("{}: needs {} from an earlier pass: {}", spec.at(), serde_json::to_value(missing)?.as_str().unwrap_or("?"), missing.remedy());
        }
        have.extend(pass.provides());
        pass.preflight(input, cx).with_context(|| spec.at())?;
    }
    Ok(())
}

#[derive(Serialize, Clone, Copy)]
pub struct Counts {
    pub nodes: usize,
    pub params: u64,
    pub macs: u64,
}

pub fn counts(model: &ModelProto) -> Result<Counts> {
    let r = inspect(model)?;
    Ok(Counts { nodes: r.nodes, params: r.params.total, macs: r.macs.total })
}

#[derive(Serialize)]
pub struct PassReport {
    pub pass: String,
    pub millis: f64,
    pub before: Counts,
    pub after: Counts,
    pub details: serde_json::Value,
}

/// Runs every pass of `recipe` on `model` in order.
pub fn run(recipe: &Recipe, model: &mut ModelProto, cx: &PassContext) -> Result<Vec<PassReport>> {
    let passes: Vec<(Box<dyn Pass>, &PassSpec)> = recipe.passes.iter().map(|s| Ok((build_pass(s).with_context(|| format!("pass {}", s.name))?, s))).collect::<Result<_>>()?;
    let mut reports = Vec::new();
    let mut before = counts(model)?;
    for (pass, spec) in passes {
        let t = Instant::now();
        let details = pass.run(model, cx).with_context(|| format!("pass {}", spec.name))?;
        let millis = t.elapsed().as_secs_f64() * 1e3;
        let after = counts(model).with_context(|| format!("after pass {}", spec.name))?;
        reports.push(PassReport { pass: pass.name().to_string(), millis, before, after, details });
        before = after;
    }
    Ok(reports)
}

/// Seconds per phase of a pass, for its report (where the time goes is a deployment concern).
pub struct Clock {
    last: Instant,
    pub laps: std::collections::BTreeMap<&'static str, f64>,
}

impl Default for Clock {
    fn default() -> Self {
        Clock { last: Instant::now(), laps: Default::default() }
    }
}

impl Clock {
    /// Books the time since the last lap (or the start) to `phase`, adding to earlier laps of it.
    pub fn lap(&mut self, phase: &'static str) {
        *self.laps.entry(phase).or_default() += self.last.elapsed().as_secs_f64();
        self.last = Instant::now();
    }
}
