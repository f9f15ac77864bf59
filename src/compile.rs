//! `pdi-compile compile`: load, run a pipeline, write a self-describing output folder.
//!
//! DIR/model.onnx      the compiled model (one self-contained file)
//! DIR/report.json     per-pass reports and before/after counts
//! DIR/manifest.yaml   what made this folder, complete enough for `rebuild` (`manifest`)
//! DIR/tract.yaml      (--target tract) tract's load/run times and agreement with ORT;
//!                     DIR/model.nnef.tar beside it when that loads faster
//! The folder is built under a temporary sibling name and moved into place whole: a failed
//! compile leaves no folder (or the previous one as it was), and a folder is never merged.

use crate::fsutil::{write_atomic, StagedDir};
use crate::onnx;
use crate::pipeline::{self, PassContext, PassReport, Recipe};
use anyhow::{Context, Result};
use serde::Serialize;
use sha2::{Digest, Sha256};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Tensors from this size up go to the external data file; smaller ones (shapes, scales,
/// biases) stay inline where tools that read the graph alone can still see them.
const EXTERNAL_THRESHOLD: usize = 1024;

pub struct CompileRequest {
    pub model: PathBuf,
    pub pipeline: PathBuf,
    pub out_dir: PathBuf,
    /// Weights go to `model.onnx.data` beside the model (needed past protobuf's 2 GiB).
    pub external_data: bool,
    pub context: PassContext,
    pub target: crate::targets::Target,
    /// Threads of the target check's timed runs (tract and ONNX Runtime alike).
    pub threads: usize,
    /// The tract target's timed choices from an earlier build (`rebuild`); None: time them.
    pub decisions: Option<crate::targets::tract::Decisions>,
    /// Paths under `.0` recorded as under `.1`: the compile runs inside a folder that is
    /// moved into place later (`ship`, `bench`), and its manifest must name where its input,
    /// recipe and output will be.
    pub moved: Option<(PathBuf, PathBuf)>,
}

impl CompileRequest {
    /// `p` as the report and manifest record it.
    fn recorded(&self, p: &Path) -> String {
        match &self.moved {
            Some((from, to)) => p.strip_prefix(from).map_or_else(|_| p.to_path_buf(), |rest| to.join(rest)),
            None => p.to_path_buf(),
        }
        .display()
        .to_string()
    }
}

#[derive(Serialize)]
pub struct CompileReport {
    pub tool_version: &'static str,
    pub input: String,
    pub input_sha256: String,
    pub pipeline: Recipe,
    pub pipeline_file: String,
    pub before: crate::inspect::Counts,
    pub after: crate::inspect::Counts,
    pub passes: Vec<PassReport>,
    /// Every warning of the compile (also printed on stderr as it happened).
    pub warnings: Vec<String>,
    /// Why a rebuild could give other bytes (a training the time cap stopped); empty: the
    /// same input, recipe, thread counts and machine give the same model.
    pub not_reproducible: Vec<String>,
    pub millis: f64,
    pub output: String,
    pub target: crate::targets::Target,
    /// What the target check measured (`--target tract`: tract.yaml's contents).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target_check: Option<serde_json::Value>,
}

pub fn compile(req: &CompileRequest) -> Result<CompileReport> {
    compile_recipe(req, Recipe::load(&req.pipeline)?)
}

/// `compile` with the recipe given (`rebuild` gives the manifest's, options resolved).
pub fn compile_recipe(req: &CompileRequest, recipe: Recipe) -> Result<CompileReport> {
    let t = Instant::now();
    if req.out_dir.exists() && !req.out_dir.is_dir() {
        anyhow::bail!("output path {} exists and is not a folder; pick another -o", req.out_dir.display());
    }
    let mut recipe = recipe;
    if let Some(scene) = &req.context.scene {
        recipe = recipe.with_scene(scene)?;
    }
    let bytes = std::fs::read(&req.model).map_err(|e| anyhow::anyhow!("cannot read {}: {e}", req.model.display()))?;
    let loaded = onnx::load_bytes(&bytes, req.model.parent().or(Some(Path::new("."))))
        .map_err(|e| anyhow::anyhow!("{}: {e:#}", req.model.display()))?;
    for w in &loaded.warnings {
        crate::warn::warn(w.clone());
    }
    let mut model = loaded.model;
    // The whole recipe, before any pass runs: options, order, what the command line supplies.
    pipeline::check(&recipe, &model, &req.context).with_context(|| format!("pipeline {}", req.pipeline.display()))?;
    // The tract target weighs INT8 against the float model it came from: keep that one.
    let split = match req.target {
        crate::targets::Target::Tract => recipe.passes.iter().position(|p| p.name == "quantize").unwrap_or(recipe.passes.len()),
        _ => recipe.passes.len(),
    };
    let (head, tail) = recipe.passes.split_at(split);
    let mut cx = req.context.clone();
    let mut passes = pipeline::run(&Recipe { passes: head.to_vec(), ..recipe.clone() }, &mut model, &mut cx)?;
    let float = (!tail.is_empty()).then(|| model.clone());
    passes.extend(pipeline::run(&Recipe { passes: tail.to_vec(), ..recipe.clone() }, &mut model, &mut cx)?);
    if let Some(scene) = &req.context.scene {
        crate::scene::record_post_processing(&mut model, scene)?;
    }
    // The runner already counted before the first pass and after each one.
    let before = match passes.first() {
        Some(p) => p.before,
        None => crate::inspect::counts(&model)?,
    };
    let after = passes.last().map_or(before, |p| p.after);

    let staged = StagedDir::new(&req.out_dir)?;
    let dir = staged.path();
    let target_check = match req.target {
        crate::targets::Target::Onnx => None,
        crate::targets::Target::Tract => {
            let (artifact, chosen) = crate::targets::tract::write(dir, model, float, req.threads, req.decisions.as_ref())?;
            model = chosen;
            Some(serde_json::to_value(artifact)?)
        }
        crate::targets::Target::Rknn => Some(serde_json::to_value(crate::targets::rknn::write(dir, &model, req.context.calib.as_deref())?)?),
    };
    let out_model = req.out_dir.join("model.onnx");
    let staged_model = dir.join("model.onnx");
    if req.external_data {
        onnx::io::save_with_external_data(&model, &staged_model, EXTERNAL_THRESHOLD)?;
    } else {
        onnx::save(&model, &staged_model)?;
    }
    let trainings = std::mem::take(&mut cx.trainings);
    let unrepeatable: Vec<String> = trainings.iter().filter_map(|a| a.not_reproducible.as_ref().map(|w| format!("{}: {w}", a.pass))).collect();
    let report = CompileReport {
        tool_version: env!("CARGO_PKG_VERSION"),
        input: req.recorded(&req.model),
        input_sha256: crate::manifest::hex(&Sha256::digest(&bytes)),
        pipeline: recipe,
        pipeline_file: req.recorded(&req.pipeline),
        before,
        after,
        passes,
        warnings: crate::warn::take().into_iter().chain(cx.warnings).collect(),
        not_reproducible: unrepeatable,
        millis: t.elapsed().as_secs_f64() * 1e3,
        output: req.recorded(&out_model),
        target: req.target,
        target_check,
    };
    write_atomic(&dir.join("report.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    write_atomic(&dir.join("manifest.yaml"), manifest(req, &report, &staged_model, trainings)?.as_bytes())?;
    staged.commit()?;
    Ok(report)
}

/// The folder's manifest; `training` is each training the passes ran.
fn manifest(req: &CompileRequest, r: &CompileReport, model: &Path, training: Vec<crate::torch::train::Account>) -> Result<String> {
    use crate::manifest::{Hashed, Host, Inputs, Manifest, Versions};
    let cx = &req.context;
    let m = Manifest {
        tool: "pdi-compile".into(),
        tool_version: r.tool_version.into(),
        input: r.input.clone(),
        input_sha256: r.input_sha256.clone(),
        model: "model.onnx".into(),
        model_sha256: crate::manifest::sha256_file(model)?,
        pipeline: pipeline::resolve(&r.pipeline)?,
        pipeline_file: r.pipeline_file.clone(),
        inputs: Inputs {
            psf: cx.psf.as_deref().map(Hashed::of).transpose()?,
            calib: cx.calib.as_deref().map(Hashed::of).transpose()?,
            keep_outputs: cx.keep_outputs.clone(),
            scene: cx.scene.clone(),
        },
        target: r.target,
        threads: req.threads,
        external_data: req.external_data,
        host: Host::this(),
        versions: Versions::of(&training),
        training,
        reproducible: r.not_reproducible.is_empty(),
        not_reproducible: r.not_reproducible.clone(),
        passes: r.passes.iter().map(serde_json::to_value).collect::<Result<_, _>>()?,
        target_check: r.target_check.clone(),
    };
    Ok(yaml_serde::to_string(&m)?)
}
