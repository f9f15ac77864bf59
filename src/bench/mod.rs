//! `pdi-compile bench MODEL -o DIR`: run time against error for every deployment variant.
//!
//! Variants: unpruned and pruned with recovery (detect-f32 / detect-pruned-f32), each in
//! f32, FP16 and INT8, and pruned without recovery (detect-pruned-f32-norecover) in f32 (the
//! passes detect-fp16 / detect-int8 / detect-pruned-int8 add to their base applied to the f32
//! compile, so pruning and the lossless passes run once), each on ONNX Runtime and tract,
//! beside the original on ONNX Runtime. Every variant is verified against the original on
//! the same frames: rel L2 of the detection outputs and mAP@0.5:0.95 agreement (the
//! original's detections as ground truth); then latency, the original and every variant on
//! every engine interleaved in one loop, so that all ratios come from the same run.
//!
//! DIR/bench.json, DIR/bench.md   the table (Pareto-optimal rows marked)
//! DIR/bench.svg, DIR/bench.png   latency against rel L2 and against mAP agreement
//! DIR/recipes/, DIR/variants/    what was compiled, and the compiled folders
//!
//! FP16 on tract is measured only where the CPU computes f16 natively (aarch64) or when
//! asked (`--tract-fp16`): on x86_64 tract emulates f16 arithmetic, and one bench run on
//! the v5 fixture measured it 16.6x slower than tract f32 (702.7 ms against 42.4 ms), which at 640x480 costs minutes per variant and tells a deployment
//! only not to do it.

pub mod plot;

use crate::compile::{compile, CompileRequest};
use crate::fsutil::{ensure_dir, write_atomic, StagedDir};
use crate::pipeline::PassContext;
use crate::runtime::Engine;
use crate::runtime::op_profile::OpProfile;
use crate::variants::{last_pass_of, own_passes_of, profile_each, recipe, time_together, with_recover_steps, Failed, Timing};
use crate::verify::{verify, VerifyRequest};
use anyhow::{anyhow, Result};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub struct BenchRequest {
    pub model: PathBuf,
    pub out: PathBuf,
    pub psf: Option<PathBuf>,
    pub calib: Option<PathBuf>,
    /// Verification frames (with labels or not); simulated when absent.
    pub data: Option<PathBuf>,
    pub frames: usize,
    pub runs: usize,
    /// Measure FP16 variants on tract even where it emulates f16.
    pub tract_fp16: bool,
    /// Time budget of the pruned variants' recovery (the recipe's when None).
    pub recover_steps: Option<usize>,
    /// Threads of every timed session, ORT and tract alike.
    pub threads: usize,
}

/// Whether tract computes f16 in hardware on this machine's architecture.
const TRACT_NATIVE_F16: bool = cfg!(target_arch = "aarch64");

#[derive(Serialize, Clone, Debug)]
pub struct Row {
    pub variant: String,
    pub engine: String,
    pub latency_ms: f64,
    /// Latency over the original's on ORT, measured in the same run.
    pub ratio_vs_original: f64,
    /// Worst detection output, against the original on ORT.
    pub rel_l2: f64,
    pub map_agreement: Option<f64>,
    pub pareto_rel_l2: bool,
    pub pareto_map: bool,
}

#[derive(Serialize)]
pub struct BenchReport {
    pub model: String,
    pub frames: String,
    pub runs: usize,
    pub threads: usize,
    pub rows: Vec<Row>,
    /// Variant/engine pairs not measured, and why.
    pub not_measured: Vec<String>,
    /// Variants whose compile ended past a lossy pass's hard limit (no artifact), and why.
    pub failed: Vec<String>,
    /// What a variant missed within its limits (an error budget), in words.
    pub notes: Vec<String>,
    /// Seconds per compile, by variant.
    pub compile_seconds: Vec<(String, f64)>,
    /// Where each timed model's run goes (per operator type and per layer), on its engine.
    pub profiles: Vec<Profiled>,
    pub seconds: f64,
}

#[derive(Serialize)]
pub struct Profiled {
    pub variant: String,
    #[serde(flatten)]
    pub profile: OpProfile,
}

pub fn bench(req: &BenchRequest) -> Result<BenchReport> {
    let t = Instant::now();
    if req.frames == 0 || req.runs == 0 {
        anyhow::bail!("--frames and --runs must be at least 1");
    }
    // Built whole beside --out and moved into place at the end (an earlier folder replaced).
    let staged = StagedDir::new(&req.out)?;
    let root = staged.path().to_path_buf();
    let recipes = root.join("recipes");
    ensure_dir(&recipes)?;
    let write_recipe = |name: &str, text: &str| -> Result<PathBuf> {
        let p = recipes.join(format!("{name}.yaml"));
        write_atomic(&p, text.as_bytes())?;
        Ok(p)
    };
    let fp16 = write_recipe("fp16", &last_pass_of(recipe("detect-fp16"), "fp16")?)?;
    let int8 = write_recipe("int8", &own_passes_of(recipe("detect-int8"), "int8")?)?;
    let pruned_int8 = write_recipe("pruned-int8", &own_passes_of(recipe("detect-pruned-int8"), "pruned-int8")?)?;
    let stages = [
        ("f32", None, write_recipe("f32", recipe("detect-f32"))?),
        ("pruned-norecover-f32", None, write_recipe("pruned-norecover-f32", recipe("detect-pruned-f32-norecover"))?),
        ("pruned-f32", None, write_recipe("pruned-f32", &with_recover_steps(recipe("detect-pruned-f32"), req.recover_steps)?)?),
        ("fp16", Some("f32"), fp16.clone()),
        ("int8", Some("f32"), int8),
        ("pruned-fp16", Some("pruned-f32"), fp16),
        ("pruned-int8", Some("pruned-f32"), pruned_int8),
    ];
    let variant_dir = |v: &str| root.join("variants").join(v);
    let mut compile_seconds = Vec::new();
    let (mut failed, mut notes) = (Failed::default(), Vec::new());
    for (name, from, recipe) in &stages {
        if failed.source_failed(name, *from) {
            continue;
        }
        eprintln!("bench: compiling {name}");
        let model = from.map_or_else(|| req.model.clone(), |f| variant_dir(f).join("model.onnx"));
        let c = Instant::now();
        let compiled = compile(&CompileRequest {
            model,
            pipeline: recipe.clone(),
            out_dir: variant_dir(name),
            external_data: false,
            context: PassContext { psf: req.psf.clone(), calib: req.calib.clone(), keep_outputs: None, ..Default::default() },
            target: crate::targets::Target::Onnx,
            threads: req.threads,
            decisions: None,
            moved: Some((staged.path().to_path_buf(), req.out.clone())),
        });
        let Some(r) = failed.take("bench", name, compiled).map_err(|e| anyhow!("compiling the {name} variant: {e:#}"))? else { continue };
        notes.extend(r.warnings.iter().filter(|w| w.contains("missed its error budget")).map(|w| format!("{name}: {w}")));
        compile_seconds.push((name.to_string(), c.elapsed().as_secs_f64()));
    }

    // Accuracy per variant against the original; latency afterwards, every model and
    // engine timed in one interleaved loop so that all ratios come from the same run.
    let mut rows = Vec::new();
    let mut not_measured = Vec::new();
    let mut timed: Vec<(String, Engine, PathBuf)> = Vec::new();
    for (name, _, _) in stages.iter().filter(|(n, _, _)| !failed.contains(n)) {
        let tract = !name.ends_with("fp16") || TRACT_NATIVE_F16 || req.tract_fp16;
        if !tract {
            not_measured.push(format!("{name} on tract: tract emulates f16 arithmetic on {} (pass --tract-fp16 to measure it anyway)", std::env::consts::ARCH));
        }
        eprintln!("bench: checking {name} on ONNX Runtime{} against the original", if tract { " and tract" } else { "" });
        let model = variant_dir(name).join("model.onnx");
        let r = verify(&VerifyRequest {
            reference: req.model.clone(),
            candidate: model.clone(),
            data: req.data.clone(),
            random: req.frames,
            psf: req.psf.clone(),
            gate: None,
            latency_runs: 0,
            tract,
            seed: 0,
            threads: req.threads,
        })
        .map_err(|e| anyhow!("measuring the {name} variant: {e:#}"))?;
        let worst = |f: &dyn Fn(&crate::verify::OutputReport) -> Option<f64>| r.outputs.iter().filter_map(f).fold(0.0, f64::max);
        let det = r.detection.as_ref();
        rows.push(Row::new(name, "ort", worst(&|o| Some(o.ort.rel_l2)), det.map(|d| d.agreement.map50_95)));
        timed.push((name.to_string(), Engine::Ort, model.clone()));
        if tract {
            rows.push(Row::new(name, "tract", worst(&|o| o.tract_vs_reference.map(|e| e.rel_l2)), det.and_then(|d| d.agreement_tract.as_ref()).map(|m| m.map50_95)));
            timed.push((name.to_string(), Engine::Tract, model));
        }
    }
    eprintln!("bench: timing the original and {} variant/engine pairs together, {} runs each", timed.len(), req.runs);
    let timing = Timing { original: &req.model, timed: &timed, data: req.data.as_deref(), psf: req.psf.as_deref(), runs: req.runs, threads: req.threads };
    let latency = time_together(&timing)?;
    eprintln!("bench: profiling each of them, per operator and layer");
    let every: Vec<(String, crate::runtime::Engine, PathBuf)> = std::iter::once(("original".to_string(), crate::runtime::Engine::Ort, req.model.clone())).chain(timed.iter().cloned()).collect();
    let profiles = profile_each(&Timing { timed: &every, ..timing })?.into_iter().map(|(variant, profile)| Profiled { variant, profile }).collect();
    let original = latency[0];
    rows.insert(0, Row::new("original", "ort", 0.0, Some(1.0)));
    for (row, ms) in rows.iter_mut().zip(&latency) {
        row.latency_ms = *ms;
        row.ratio_vs_original = ms / original;
    }
    mark_pareto(&mut rows);

    let report = BenchReport {
        model: req.model.display().to_string(),
        frames: req.data.as_ref().map_or(format!("{} synthetic frames, seed 0", req.frames), |d| d.display().to_string()),
        runs: req.runs,
        threads: req.threads,
        rows,
        not_measured,
        failed: failed.lines(),
        notes,
        compile_seconds,
        profiles,
        seconds: 0.0,
    };
    let svg = plot::svg(&report.rows, &report.model);
    let png = plot::png(&report.rows, &report.model)?;
    let report = BenchReport { seconds: t.elapsed().as_secs_f64(), ..report };
    write_atomic(&root.join("bench.json"), serde_json::to_string_pretty(&report)?.as_bytes())?;
    write_atomic(&root.join("bench.md"), report.markdown().as_bytes())?;
    write_atomic(&root.join("bench.svg"), svg.as_bytes())?;
    write_atomic(&root.join("bench.png"), &png)?;
    staged.commit()?;
    Ok(report)
}

impl Row {
    fn new(variant: &str, engine: &str, rel_l2: f64, map_agreement: Option<f64>) -> Row {
        Row { variant: variant.into(), engine: engine.into(), latency_ms: 0.0, ratio_vs_original: 0.0, rel_l2, map_agreement, pareto_rel_l2: false, pareto_map: false }
    }
}

/// A row is Pareto-optimal when no other row is at least as fast and at least as accurate,
/// and strictly better in one of the two.
fn mark_pareto(rows: &mut [Row]) {
    let snapshot = rows.to_vec();
    let dominated = |r: &Row, err: &dyn Fn(&Row) -> f64| snapshot.iter().any(|o| o.latency_ms <= r.latency_ms && err(o) <= err(r) && (o.latency_ms < r.latency_ms || err(o) < err(r)));
    for r in rows.iter_mut() {
        r.pareto_rel_l2 = !dominated(r, &|x| x.rel_l2);
        r.pareto_map = r.map_agreement.is_some() && !dominated(r, &|x| -x.map_agreement.unwrap_or(f64::NEG_INFINITY));
    }
}

impl BenchReport {
    pub fn markdown(&self) -> String {
        let mut s = format!("# pdi-compile bench: {}\n\n{} ; median of {} runs per model on {} threads (ORT and tract alike), all models interleaved in one loop.\n`*` marks the Pareto front (latency against rel L2 / against mAP agreement).\n\n", self.model, self.frames, self.runs, self.threads);
        s += "| variant | engine | latency ms | vs original | rel L2 | mAP agreement |\n|---|---|---:|---:|---:|---:|\n";
        for r in &self.rows {
            let map = r.map_agreement.map_or("-".to_string(), |m| format!("{m:.4}{}", if r.pareto_map { " *" } else { "" }));
            s += &format!("| {} | {} | {:.1} | {:.3} | {:.2e}{} | {} |\n", r.variant, r.engine, r.latency_ms, r.ratio_vs_original, r.rel_l2, if r.pareto_rel_l2 { " *" } else { "" }, map);
        }
        for n in &self.not_measured {
            s += &format!("\nNot measured: {n}.");
        }
        for f in &self.failed {
            s += &format!("\nFAILED, no artifact: {f}.");
        }
        for n in &self.notes {
            s += &format!("\nNote: {n}.");
        }
        if !self.profiles.is_empty() {
            s += "\n\n## Where the time goes\n\nEach model profiled on its engine (its own runs, not the loop above): the three operator types and layers that take the most of its kernels' time; a layer's GMAC/s against the best any layer reached on that engine here, and the activation bytes it moved per second.\n\n| variant | engine | run ms | GMAC/s (best layer) | top operators | top layers |\n|---|---|---:|---:|---|---|\n";
            for p in &self.profiles {
                let f = &p.profile;
                let ops = f.by_op.iter().take(3).map(|o| format!("{} {:.0}%", o.op, o.share * 100.0)).collect::<Vec<_>>().join(", ");
                let layers = f.layers.iter().take(3).map(|l| format!("`{}` {:.2} ms ({}, {:.1} GB/s)", l.node, l.ms, l.gmacs_per_s.map_or("no MACs".into(), |g| format!("{g:.1} GMAC/s")), l.gbytes_per_s)).collect::<Vec<_>>().join("; ");
                s += &format!("| {} | {} | {:.1} | {:.1} ({:.1}) | {ops} | {layers} |\n", p.variant, f.engine.as_str(), f.run_ms, f.gmacs_per_s, f.best_gmacs_per_s);
            }
        }
        s += "\n\nCompile seconds: ";
        s += &self.compile_seconds.iter().map(|(v, t)| format!("{v} {t:.1}")).collect::<Vec<_>>().join(", ");
        s += &format!("; total {:.0} s.\n", self.seconds);
        s
    }
}

/// For `bench`'s CLI summary.
pub fn out_files(dir: &Path) -> String {
    ["bench.md", "bench.json", "bench.svg", "bench.png"].iter().map(|f| dir.join(f).display().to_string()).collect::<Vec<_>>().join(", ")
}
