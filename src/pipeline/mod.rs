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

pub trait Pass {
    fn name(&self) -> &'static str;
    /// Rewrites `model`; returns the pass's own report.
    fn run(&self, model: &mut ModelProto, cx: &PassContext) -> Result<serde_json::Value>;
}

pub fn build_pass(spec: &PassSpec) -> Result<Box<dyn Pass>> {
    crate::passes::build(spec)
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
    let passes: Vec<(Box<dyn Pass>, &PassSpec)> = recipe.passes.iter().map(|s| Ok((build_pass(s)?, s))).collect::<Result<_>>()?;
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
