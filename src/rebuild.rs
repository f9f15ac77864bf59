//! `pdi-compile rebuild DIR -o DIR2`: compiles again from DIR's manifest alone (the input and
//! the files the compile read, checked against their recorded hashes; the recipe with every
//! option resolved; the scene, target and threads; the tract target's timed choices reused)
//! and compares. On the host that built DIR (same CPU and core count) a reproducible build
//! must give the same model bytes; elsewhere, or when DIR's training was stopped by its time
//! cap, the two models are compared by `verify`, and the report says which comparison it made.

use crate::compile::{compile_recipe, CompileRequest};
use crate::manifest::{self, Hashed, Host};
use crate::pipeline::PassContext;
use anyhow::{bail, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};

pub struct RebuildRequest {
    pub dir: PathBuf,
    pub out: PathBuf,
    /// Frames for the `verify` comparison (simulated when None).
    pub data: Option<PathBuf>,
}

#[derive(Serialize)]
pub struct RebuildReport {
    pub from: String,
    pub to: String,
    /// `bytes` (same host, reproducible build) or `verify` (and why).
    pub compared_by: String,
    pub original_sha256: String,
    pub rebuilt_sha256: String,
    pub identical: bool,
    /// With `verify`: the worst output rel L2 and lowest cosine against the first build on
    /// ONNX Runtime, and the detections' agreement mAP@0.5:0.95.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub worst_rel_l2: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub min_cosine: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub agreement: Option<f64>,
    /// Whether the rebuild holds: identical bytes when compared by bytes; with `verify`, it
    /// is a measurement, and passes.
    pub passed: bool,
}

pub fn rebuild(req: &RebuildRequest) -> Result<RebuildReport> {
    let m = manifest::load(&req.dir)?;
    let input = PathBuf::from(&m.input);
    let sha = manifest::sha256_file(&input).map_err(|_| anyhow::anyhow!("the input {} that {} was built from is not there (paths are as the first compile was given them: run rebuild from the same folder)", m.input, req.dir.display()))?;
    if sha != m.input_sha256 {
        bail!("the input {} changed since {} was built (sha256 {} now, {} then)", m.input, req.dir.display(), &sha[..12], &m.input_sha256[..12.min(m.input_sha256.len())]);
    }
    let same_file = |recorded: &Option<Hashed>, what: &str| -> Result<Option<PathBuf>> {
        let Some(r) = recorded else { return Ok(None) };
        let now = Hashed::of(Path::new(&r.path)).map_err(|e| anyhow::anyhow!("{what} {}: {e:#}", r.path))?;
        if now.sha256 != r.sha256 {
            bail!("{what} {} changed since {} was built ({} file(s) then, {} now)", r.path, req.dir.display(), r.files, now.files);
        }
        Ok(Some(PathBuf::from(&r.path)))
    };
    let psf = same_file(&m.inputs.psf, "--psf")?;
    let calib = same_file(&m.inputs.calib, "--calib")?;
    let decisions = (m.target == crate::targets::Target::Tract).then(|| m.target_check.as_ref().map(crate::targets::tract::Decisions::recorded)).flatten();
    let compile = CompileRequest {
        model: input,
        pipeline: PathBuf::from(&m.pipeline_file),
        out_dir: req.out.clone(),
        external_data: m.external_data,
        context: PassContext { psf: psf.clone(), calib, keep_outputs: m.inputs.keep_outputs.clone(), scene: m.inputs.scene.clone(), ..Default::default() },
        target: m.target,
        threads: m.threads,
        decisions,
        moved: None,
    };
    // The manifest's recipe already has the scene's passes in place; with_scene keeps them.
    let mut recipe = with_recorded_ratios(&m)?;
    pin_recorded_threads(&mut recipe, &m.training);
    compile_recipe(&compile, recipe)?;
    let original = req.dir.join(&m.model);
    let rebuilt = req.out.join("model.onnx");
    let rebuilt_sha256 = manifest::sha256_file(&rebuilt)?;
    let identical = rebuilt_sha256 == m.model_sha256;
    let same_host = Host::this() == m.host;
    let base = RebuildReport {
        from: req.dir.display().to_string(),
        to: req.out.display().to_string(),
        compared_by: String::new(),
        original_sha256: m.model_sha256.clone(),
        rebuilt_sha256,
        identical,
        worst_rel_l2: None,
        min_cosine: None,
        agreement: None,
        passed: identical,
    };
    if same_host && m.reproducible {
        return Ok(RebuildReport { compared_by: format!("bytes: the same host ({}, {} cores) and a reproducible build", m.host.cpu, m.host.cores), ..base });
    }
    let why = if !m.reproducible { format!("verify: the first build was not reproducible ({})", m.not_reproducible.join("; ")) } else { format!("verify: built on another host ({}, {} cores; this one: {}, {} cores)", m.host.cpu, m.host.cores, Host::this().cpu, Host::this().cores) };
    let v = crate::verify::verify(&crate::verify::VerifyRequest {
        reference: original,
        candidate: rebuilt,
        data: req.data.clone(),
        random: 8,
        psf,
        gate: None,
        latency_runs: 0,
        tract: false,
        seed: 0,
        threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
    })?;
    Ok(RebuildReport {
        compared_by: why,
        worst_rel_l2: Some(v.outputs.iter().map(|o| o.ort.rel_l2).fold(0.0, f64::max)),
        min_cosine: Some(v.outputs.iter().map(|o| o.ort.cosine).fold(1.0, f64::min)),
        agreement: v.detection.as_ref().map(|d| d.agreement.map50_95),
        passed: true,
        ..base
    })
}

/// The manifest's recipe with each `prune: {target: {latency}}` replaced by the per-group
/// ratios that build's timing chose (its report's sensitivity groups), so that the rebuild
/// does not time again.
fn with_recorded_ratios(m: &manifest::Manifest) -> Result<crate::pipeline::Recipe> {
    let mut recipe = m.pipeline.clone();
    let reports: Vec<&serde_json::Value> = m.passes.iter().collect();
    if reports.len() != recipe.passes.len() {
        bail!("{} lists {} pass reports for {} passes: not a manifest this version wrote", m.pipeline_file, reports.len(), recipe.passes.len());
    }
    for (spec, report) in recipe.passes.iter_mut().zip(reports) {
        let timed = spec.options.get("target").and_then(|t| t.get("latency")).is_some_and(|l| !l.is_null());
        if spec.name != "prune" || !timed {
            continue;
        }
        let groups = report["details"]["sensitivity"]["groups"].as_array().ok_or_else(|| anyhow::anyhow!("the recorded prune report has no sensitivity groups to reuse"))?;
        let mut ratios = yaml_serde::Mapping::new();
        for g in groups.iter().filter(|g| g["chosen"].as_f64().is_some_and(|c| c > 0.0)) {
            ratios.insert(g["anchor"].as_str().unwrap_or_default().into(), g["chosen"].as_f64().unwrap_or_default().into());
        }
        if let yaml_serde::Value::Mapping(o) = &mut spec.options {
            o.insert("target".into(), yaml_serde::Value::Null);
            o.insert("ratios".into(), yaml_serde::Value::Mapping(ratios));
            // The bounds shaped what the timing chose; they bound no target now.
            o.remove("max_ratios");
        }
    }
    Ok(recipe)
}

/// Sets each training's `threads: 0` (every core of the compiling machine, or its share of
/// them when workers ran side by side: `pyenv::worker_share`) to the count that training
/// recorded, so that a rebuild trains with the same sums whatever runs beside it. The
/// trainings of one pass name are matched to the passes of that name in order.
fn pin_recorded_threads(recipe: &mut crate::pipeline::Recipe, training: &[crate::torch::train::Account]) {
    let mut used = vec![false; training.len()];
    for spec in &mut recipe.passes {
        // The schedule's keys sit flat in the pass's options, or under `qat` (`quantize`).
        let in_qat = spec.options.get("qat").is_some_and(yaml_serde::Value::is_mapping);
        let options = if in_qat { spec.options.get_mut("qat") } else { Some(&mut spec.options) };
        let Some(yaml_serde::Value::Mapping(o)) = options else { continue };
        let Some(threads) = o.get("threads").and_then(yaml_serde::Value::as_u64) else { continue };
        let Some(k) = (0..training.len()).find(|&k| !used[k] && training[k].pass == spec.name) else { continue };
        used[k] = true;
        if threads != 0 {
            continue;
        }
        let devices = o.get("devices").and_then(yaml_serde::Value::as_u64).unwrap_or(1).max(1);
        o.insert("threads".into(), (training[k].threads as u64 * devices).into());
    }
}

impl RebuildReport {
    pub fn render(&self) -> String {
        let mut s = format!("rebuilt {} -> {}\n  compared by {}\n", self.from, self.to, self.compared_by);
        if self.identical {
            s += &format!("  model.onnx identical (sha256 {})\n", &self.rebuilt_sha256[..16]);
        } else {
            s += &format!("  model.onnx differs: sha256 {} then, {} now\n", &self.original_sha256[..16.min(self.original_sha256.len())], &self.rebuilt_sha256[..16]);
        }
        if let (Some(e), Some(c)) = (self.worst_rel_l2, self.min_cosine) {
            s += &format!("  against the first build on ONNX Runtime: worst output rel L2 {e:.3e}, lowest cosine {c:.6}");
            if let Some(a) = self.agreement {
                s += &format!(", detections' agreement mAP@.5:.95 {a:.4}");
            }
            s += "\n";
        }
        s += if self.passed { "rebuild holds\n" } else { "rebuild FAILED: the same host and recipe gave other bytes\n" };
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::torch::train::Account;

    fn account(pass: &str, threads: usize) -> Account {
        Account { pass: pass.into(), device: "cpu".into(), threads, torch: "2.4".into(), steps: 1, steps_planned: 1, capped: false, not_reproducible: None }
    }

    #[test]
    fn trainings_on_every_core_rebuild_on_the_count_they_recorded() {
        let mut recipe = crate::pipeline::Recipe::parse(
            "name: r\npasses:\n  - recover: {threads: 0, devices: 2}\n  - recover: {threads: 3}\n  - recover: {threads: 0}\n  - quantize: {qat: {threads: 0}}\n  - quantize: {}\n",
        )
        .unwrap();
        // Per rank, as the worker reports it: the first recover ran 2 ranks of 1 thread.
        pin_recorded_threads(&mut recipe, &[account("recover", 1), account("recover", 3), account("recover", 2), account("quantize", 1)]);
        let threads = |k: usize, path: &[&str]| path.iter().fold(&recipe.passes[k].options, |v, key| &v[*key]).as_u64();
        assert_eq!(threads(0, &["threads"]), Some(2));
        assert_eq!(threads(1, &["threads"]), Some(3));
        // The recover that asked for 3 took its own account; the third gets the third.
        assert_eq!(threads(2, &["threads"]), Some(2));
        assert_eq!(threads(3, &["qat", "threads"]), Some(1));
        assert_eq!(threads(4, &["threads"]), None);
    }
}
