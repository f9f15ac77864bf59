//! `pdi-compile compile`: load, run a pipeline, write a self-describing output folder.
//!
//! DIR/model.onnx      the compiled model (one self-contained file)
//! DIR/report.json     per-pass reports and before/after counts
//! DIR/manifest.yaml   input hash, pipeline, tool version, target: what made this folder
//! DIR/tract.yaml      (--target tract) tract's load/run times and agreement with ORT;
//!                     DIR/model.nnef.tar beside it when that loads faster
//! Every file is written to a temp name and renamed, so a failed compile leaves no half file.

use crate::fsutil::{ensure_dir, write_atomic};
use crate::onnx;
use crate::pipeline::{self, PassContext, PassReport, Recipe};
use anyhow::Result;
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
}

#[derive(Serialize)]
pub struct CompileReport {
    pub tool_version: &'static str,
    pub input: String,
    pub input_sha256: String,
    pub pipeline: Recipe,
    pub pipeline_file: String,
    pub before: pipeline::Counts,
    pub after: pipeline::Counts,
    pub passes: Vec<PassReport>,
    /// Every warning of the compile (also printed on stderr as it happened).
    pub warnings: Vec<String>,
    pub millis: f64,
    pub output: String,
    pub target: crate::targets::Target,
    /// What the target check measured (`--target tract`: tract.yaml's contents).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub target_check: Option<serde_json::Value>,
}

pub fn compile(req: &CompileRequest) -> Result<CompileReport> {
    let t = Instant::now();
    let mut recipe = Recipe::load(&req.pipeline)?;
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
    // The tract target weighs INT8 against the float model it came from: keep that one.
    let split = match req.target {
        crate::targets::Target::Tract => recipe.passes.iter().position(|p| p.name == "quantize").unwrap_or(recipe.passes.len()),
        _ => recipe.passes.len(),
    };
    let (head, tail) = recipe.passes.split_at(split);
    let mut passes = pipeline::run(&Recipe { passes: head.to_vec(), ..recipe.clone() }, &mut model, &req.context)?;
    let float = (!tail.is_empty()).then(|| model.clone());
    passes.extend(pipeline::run(&Recipe { passes: tail.to_vec(), ..recipe.clone() }, &mut model, &req.context)?);
    // Passes list their warnings in their details; they join the top-level list (and stderr).
    for p in &passes {
        for w in p.details["warnings"].as_array().into_iter().flatten().filter_map(|w| w.as_str()) {
            crate::warn::warn(format!("{}: {w}", p.pass));
        }
    }
    if let Some(scene) = &req.context.scene {
        crate::scene::record_post_processing(&mut model, scene)?;
    }
    // The runner already counted before the first pass and after each one.
    let before = match passes.first() {
        Some(p) => p.before,
        None => pipeline::counts(&model)?,
    };
    let after = passes.last().map_or(before, |p| p.after);

    ensure_dir(&req.out_dir)?;
    // The target check runs first: a model the target cannot take leaves no model.onnx behind.
    let target_check = match req.target {
        crate::targets::Target::Onnx => None,
        crate::targets::Target::Tract => {
            let (artifact, chosen) = crate::targets::tract::write(&req.out_dir, model, float, req.threads)?;
            model = chosen;
            Some(serde_json::to_value(artifact)?)
        }
        crate::targets::Target::Rknn => Some(serde_json::to_value(crate::targets::rknn::write(&req.out_dir, &model, req.context.calib.as_deref())?)?),
    };
    let out_model = req.out_dir.join("model.onnx");
    if req.external_data {
        onnx::io::save_with_external_data(&model, &out_model, EXTERNAL_THRESHOLD)?;
    } else {
        onnx::save(&model, &out_model)?;
    }
    let report = CompileReport {
        tool_version: env!("CARGO_PKG_VERSION"),
        input: req.model.display().to_string(),
        input_sha256: hex(&Sha256::digest(&bytes)),
        pipeline: recipe,
        pipeline_file: req.pipeline.display().to_string(),
        before,
        after,
        passes,
        warnings: crate::warn::take(),
        millis: t.elapsed().as_secs_f64() * 1e3,
        output: out_model.display().to_string(),
        target: req.target,
        target_check,
    };
    write_atomic(&req.out_dir.join("report.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    write_atomic(&req.out_dir.join("manifest.yaml"), manifest(&report, &out_model)?.as_bytes())?;
    Ok(report)
}

fn manifest(r: &CompileReport, model: &Path) -> Result<String> {
    #[derive(Serialize)]
    struct Manifest<'a> {
        tool: &'static str,
        tool_version: &'a str,
        input: &'a str,
        input_sha256: &'a str,
        model: &'static str,
        model_sha256: String,
        pipeline: &'a Recipe,
        passes: &'a [PassReport],
        target: crate::targets::Target,
        #[serde(skip_serializing_if = "Option::is_none")]
        target_check: Option<&'a serde_json::Value>,
    }
    let m = Manifest {
        tool: "pdi-compile",
        tool_version: r.tool_version,
        input: &r.input,
        input_sha256: &r.input_sha256,
        model: "model.onnx",
        model_sha256: hex(&Sha256::digest(std::fs::read(model)?)),
        pipeline: &r.pipeline,
        passes: &r.passes,
        target: r.target,
        target_check: r.target_check.as_ref(),
    };
    Ok(yaml_serde::to_string(&m)?)
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}
