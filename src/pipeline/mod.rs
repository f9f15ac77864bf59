//! Pass pipelines: YAML recipes naming passes and their options, checked whole, then run in
//! order.
//!
//! A pass (`passes::Pass`) takes a model, rewrites it, and reports what it did
//! (`serde_json::Value`, pass-specific). The runner adds what every pass report carries: time
//! taken, node/parameter/MAC counts before and after, and the pass's warnings.

pub mod preview;
pub mod recipe;

use crate::inspect::{counts, Counts};
use crate::onnx::proto::ModelProto;
use anyhow::{Context, Result};
use serde::Serialize;
use std::time::Instant;

pub use crate::passes::{is_quality_failure, Capability, Pass, PassContext, QualityFailure, Teacher};
pub use recipe::{PassSpec, Recipe};

pub fn build_pass(spec: &PassSpec) -> Result<Box<dyn Pass>> {
    let built = crate::passes::build(&spec.name, &spec.options)?;
    built.pass.check()?;
    Ok(built.pass)
}

/// `recipe` with every pass's options resolved (defaults filled in): what the manifest
/// records, and what a rebuild runs.
pub fn resolve(recipe: &Recipe) -> Result<Recipe> {
    let mut out = recipe.clone();
    for p in &mut out.passes {
        p.options = crate::passes::build(&p.name, &p.options).with_context(|| format!("pass {}", p.name))?.options;
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


#[derive(Serialize)]
pub struct PassReport {
    pub pass: String,
    pub millis: f64,
    pub before: Counts,
    pub after: Counts,
    pub details: serde_json::Value,
    /// What the pass warned of ([`PassContext::warn`]), each as "pass: what".
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
}

/// Runs every pass of `recipe` on `model` in order.
pub fn run(recipe: &Recipe, model: &mut ModelProto, cx: &mut PassContext) -> Result<Vec<PassReport>> {
    let passes: Vec<Box<dyn Pass>> = recipe.passes.iter().map(|s| crate::passes::build(&s.name, &s.options).map(|b| b.pass).with_context(|| format!("pass {}", s.name))).collect::<Result<_>>()?;
    run_passes(passes, model, cx)
}

/// Runs `passes` on `model` in order, each option-checked before any runs; each report has
/// the pass's time, the counts before and after, and its warnings.
pub fn run_passes(passes: Vec<Box<dyn Pass>>, model: &mut ModelProto, cx: &mut PassContext) -> Result<Vec<PassReport>> {
    for pass in &passes {
        pass.check().with_context(|| format!("pass {}", pass.name()))?;
    }
    let mut reports = Vec::new();
    let mut before = counts(model)?;
    for pass in passes {
        let t = Instant::now();
        // narrow-convs-nchw's 3-D convolutions and pinned biases, and space-to-depth's
        // blocks, go back for every pass but those that take them.
        let lowered = match model.graph.as_mut() {
            Some(g) => {
                let convs = if pass.takes_lifted_convs() { 0 } else { crate::ir::rewrite::lower_narrow_forms(g)? };
                convs + if pass.takes_space_to_depth() { 0 } else { crate::ir::rewrite::space_to_depth::lower_all(g)? }
            }
            None => 0,
        };
        if lowered > 0 {
            before = counts(model)?;
        }
        cx.pass = pass.name();
        let warned = cx.warnings.len();
        let details = pass.run(model, cx).with_context(|| format!("pass {}", pass.name()))?;
        let millis = t.elapsed().as_secs_f64() * 1e3;
        let after = counts(model).with_context(|| format!("after pass {}", pass.name()))?;
        reports.push(PassReport { pass: pass.name().to_string(), millis, before, after, details, warnings: cx.warnings[warned..].to_vec() });
        before = after;
    }
    Ok(reports)
}

