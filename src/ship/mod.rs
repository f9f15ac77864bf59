//! `pdi-compile ship MODEL -o DIR`: the deployment artifacts of one trained model, measured.
//!
//! Builds, each in its own self-describing folder (model, report.json, manifest.yaml):
//!   DIR/f32           the lossless detection compile, with the tract target (tract.yaml)
//!   DIR/pruned-f32    pruned to 30% of the MACs in 16-channel steps, recovered by distillation,
//!                     with the tract target
//!   DIR/pruned-int8   that model in INT8 (QDQ, for ONNX Runtime on x86)
//!   DIR/rknn          that model legalized for the RK3588 NPU, with the RKNN target
//! then checks the ONNX variants against the original on the same frames (mAP against labels
//! when the frames have them, agreement with the original's detections otherwise) and times
//! the original and every variant on ONNX Runtime and tract in one interleaved loop.
//! Writes DIR/ship.json; [`render`] is the one screen a person reads.
//!
//! Pruning runs once: INT8 and the NPU build start from the same recovered pruned model, so
//! what the CPU runs and what the NPU runs differ only by their last pass.

pub mod recommend;
pub mod render;

use crate::variants::{last_pass_of, own_passes_of, recipe, time_together, with_recover_steps, Failed, Timing};
use crate::compile::{compile, CompileReport, CompileRequest};
use crate::fsutil::{ensure_dir, write_atomic, StagedDir};
use crate::pipeline::{PassContext, Recipe};
use crate::runtime::Engine;
use crate::targets::Target;
use crate::verify::{verify, VerifyRequest};
use anyhow::{anyhow, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub struct ShipRequest {
    pub model: PathBuf,
    pub out: PathBuf,
    pub psf: Option<PathBuf>,
    pub calib: Option<PathBuf>,
    /// Frames to check on (YOLO labels beside them give mAP against labels).
    pub data: Option<PathBuf>,
    /// Simulated frames when no --data is given.
    pub frames: usize,
    pub recover_steps: Option<usize>,
    pub runs: usize,
    /// The share of the original's mAP an artifact must keep to be recommended for a CPU.
    pub min_kept: f64,
    pub threads: usize,
}

#[derive(Serialize)]
pub struct Variant {
    pub name: String,
    pub folder: String,
    pub file: String,
    pub bytes: u64,
    pub macs: u64,
    pub params: u64,
    pub ort_ms: Option<f64>,
    pub tract_ms: Option<f64>,
    /// mAP@0.5:0.95 against the frames' labels (on ORT), when they have labels.
    pub map_labels: Option<f64>,
    /// mAP@0.5:0.95 agreement with the original's detections, on ORT and on tract.
    pub agreement: Option<f64>,
    pub agreement_tract: Option<f64>,
    pub compile_seconds: f64,
    /// What the variant missed within its limits (an error budget), in words.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

#[derive(Serialize)]
pub struct ShipReport {
    pub model: String,
    pub out: String,
    pub frames: String,
    pub threads: usize,
    pub runs: usize,
    pub variants: Vec<Variant>,
    /// The RKNN folder and what it holds (the toolkit builds model.rknn from it).
    pub rknn: String,
    /// Variants whose compile ended past a lossy pass's hard limit (no artifact), and why.
    pub failed: Vec<String>,
    pub warnings: Vec<String>,
    /// The artifact to deploy on each target, and the measurement that chose it.
    pub recommended: Vec<recommend::Recommendation>,
    pub seconds: f64,
}

/// The compiles: (name, source variant or the original, recipe text, target).
fn stages(req: &ShipRequest) -> Result<Vec<(&'static str, Option<&'static str>, String, Target)>> {
    // The NPU recipe without its legalization: pruned in 16-channel steps, recovered.
    let mut pruned = Recipe::parse(&with_recover_steps(recipe("detect-pruned-rknn"), req.recover_steps)?)?;
    pruned.passes.retain(|p| p.name != "rknn-legalize");
    pruned.name = "pruned-f32".into();
    Ok(vec![
        ("f32", None, recipe("detect-f32").to_string(), Target::Tract),
        ("pruned-f32", None, pruned.to_yaml()?, Target::Tract),
        ("pruned-int8", Some("pruned-f32"), own_passes_of(recipe("detect-pruned-int8"), "pruned-int8")?, Target::Onnx),
        ("rknn", Some("pruned-f32"), last_pass_of(recipe("detect-pruned-rknn"), "rknn")?, Target::Rknn),
    ])
}

pub fn ship(req: &ShipRequest) -> Result<ShipReport> {
    let started = Instant::now();
    // Built whole beside --out and moved into place at the end (an earlier folder replaced).
    let staged = StagedDir::new(&req.out)?;
    let root = staged.path().to_path_buf();
    let recipes = root.join("recipes");
    ensure_dir(&recipes)?;
    let folder = |v: &str| root.join(v);
    let mut compiled: Vec<(&str, CompileReport, f64)> = Vec::new();
    let mut warnings = Vec::new();
    let mut failed = Failed::default();
    for (name, from, recipe, target) in stages(req)? {
        if failed.source_failed(name, from) {
            continue;
        }
        eprintln!("ship: compiling {name}");
        let path = recipes.join(format!("{name}.yaml"));
        write_atomic(&path, recipe.as_bytes())?;
        let model = from.map_or_else(|| req.model.clone(), |f| folder(f).join("model.onnx"));
        let t = Instant::now();
        let report = compile(&CompileRequest {
            model,
            pipeline: path,
            out_dir: folder(name),
            external_data: false,
            context: PassContext { psf: req.psf.clone(), calib: req.calib.clone(), keep_outputs: None, ..Default::default() },
            target,
            threads: req.threads,
            decisions: None,
            moved: Some((root.clone(), req.out.clone())),
        });
        let Some(report) = failed.take("ship", name, report).map_err(|e| anyhow!("compiling {name}: {e:#}"))? else { continue };
        warnings.extend(report.warnings.iter().map(|w| format!("{name}: {w}")));
        compiled.push((name, report, t.elapsed().as_secs_f64()));
    }

    let onnx_variants: Vec<&str> = ["f32", "pruned-f32", "pruned-int8"].into_iter().filter(|v| !failed.contains(v)).collect();
    let mut variants = vec![original(req)?];
    for (name, report, seconds) in compiled.iter().filter(|(n, _, _)| onnx_variants.contains(n)) {
        eprintln!("ship: checking {name} against the original");
        let model = folder(name).join("model.onnx");
        let r = verify(&VerifyRequest {
            reference: req.model.clone(),
            candidate: model.clone(),
            data: req.data.clone(),
            random: req.frames,
            psf: req.psf.clone(),
            gate: None,
            latency_runs: 0,
            tract: true,
            seed: 0,
            threads: req.threads,
        })
        .map_err(|e| anyhow!("checking {name}: {e:#}"))?;
        let d = r.detection.as_ref();
        if variants[0].map_labels.is_none() {
            variants[0].map_labels = d.and_then(|d| d.reference_vs_labels.as_ref()).map(|m| m.map50_95);
        }
        variants.push(Variant {
            name: name.to_string(),
            folder: req.out.join(name).display().to_string(),
            file: if folder(name).join("model.nnef.tar").exists() { "model.nnef.tar (tract), model.onnx".into() } else { "model.onnx".into() },
            bytes: std::fs::metadata(&model)?.len(),
            macs: report.after.macs,
            params: report.after.params,
            ort_ms: None,
            tract_ms: None,
            map_labels: d.and_then(|d| d.candidate_vs_labels.as_ref()).map(|m| m.map50_95),
            agreement: d.map(|d| d.agreement.map50_95),
            agreement_tract: d.and_then(|d| d.agreement_tract.as_ref()).map(|m| m.map50_95),
            compile_seconds: *seconds,
            note: report.warnings.iter().find(|w| w.contains("missed its error budget")).cloned(),
        });
    }

    eprintln!("ship: timing the original and {} variants on ONNX Runtime and tract together, {} runs each", onnx_variants.len(), req.runs);
    let timed: Vec<(String, Engine, PathBuf)> = onnx_variants.iter().flat_map(|v| [Engine::Ort, Engine::Tract].map(|e| (v.to_string(), e, folder(v).join("model.onnx")))).collect();
    let ms = time_together(&Timing { original: &req.model, timed: &timed, data: req.data.as_deref(), psf: req.psf.as_deref(), runs: req.runs, threads: req.threads })?;
    variants[0].ort_ms = Some(ms[0]);
    for ((name, engine, _), ms) in timed.iter().zip(&ms[1..]) {
        let v = variants.iter_mut().find(|v| &v.name == name).expect("every timed variant was checked");
        match engine {
            Engine::Ort => v.ort_ms = Some(*ms),
            Engine::Tract => v.tract_ms = Some(*ms),
        }
    }
    let rknn = req.out.join("rknn");
    let recommended = recommend::recommend(&variants, req.min_kept, &rknn, failed.contains("rknn"));
    let report = ShipReport {
        model: req.model.display().to_string(),
        out: req.out.display().to_string(),
        frames: req.data.as_ref().map_or(format!("{} simulated frames", req.frames), |d| d.display().to_string()),
        threads: req.threads,
        runs: req.runs,
        variants,
        rknn: rknn.display().to_string(),
        failed: failed.lines(),
        warnings: warnings.into_iter().chain(crate::warn::take()).collect(),
        recommended,
        seconds: started.elapsed().as_secs_f64(),
    };
    write_atomic(&root.join("ship.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    staged.commit()?;
    Ok(report)
}

/// The original's row: its size and cost; latency and mAP are filled in by the checks.
fn original(req: &ShipRequest) -> Result<Variant> {
    let loaded = crate::onnx::io::load(&req.model)?;
    let r = crate::inspect::inspect(&loaded.model)?;
    Ok(Variant {
        name: "original".into(),
        folder: req.model.parent().unwrap_or(Path::new(".")).display().to_string(),
        file: req.model.file_name().map_or(String::new(), |f| f.to_string_lossy().into_owned()),
        bytes: std::fs::metadata(&req.model)?.len(),
        macs: r.macs.total,
        params: r.params.total,
        ort_ms: None,
        tract_ms: None,
        map_labels: None,
        agreement: Some(1.0),
        agreement_tract: None,
        compile_seconds: 0.0,
        note: None,
    })
}
