//! The command line. Errors surface as one line on stderr and exit code 2.

use crate::compile::{compile, CompileRequest};
use crate::pipeline::PassContext;
use anyhow::Result;
use clap::{Parser, Subcommand};
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "pdi-compile", version, about = "Compile PDI-Net ONNX models for RK3588 NPUs and tract")]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Show inputs, outputs, costs split by reconstruction/detection, the PALS-Bridge and the head.
    Inspect {
        model: PathBuf,
        /// Machine-readable report (fields documented in README.md).
        #[arg(long)]
        json: bool,
        /// Preview what a scene file (classes, object_px, roi) would remove: MACs,
        /// parameters, outputs, each key alone and all together.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Camera blur map, for a model whose blur map is a graph input (with --scene).
        #[arg(long)]
        psf: Option<PathBuf>,
        /// Calibration frames for drop-strides' measurement (with --scene).
        #[arg(long)]
        calib: Option<PathBuf>,
    },
    /// Where a model's run time goes on each engine: per operator type and per layer, with each
    /// layer's MACs, the activation bytes it moves, and the GMAC/s it reaches. With several
    /// models, first all of them timed in one interleaved loop (ratios against the first).
    Profile {
        #[arg(required = true)]
        models: Vec<PathBuf>,
        /// Engines to profile (default: both).
        #[arg(long, value_enum, value_delimiter = ',')]
        engine: Vec<crate::runtime::Engine>,
        /// Camera blur map, for a model whose blur map is a graph input.
        #[arg(long)]
        psf: Option<PathBuf>,
        /// A folder of frames: the first is run (default: a simulated frame).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Threads for ONNX Runtime and tract alike (default: every core).
        #[arg(long)]
        threads: Option<usize>,
        /// Timed runs per model and engine in the interleaved loop (with several models).
        #[arg(long, default_value_t = 20)]
        runs: usize,
        /// Print the profiles as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Run a pass pipeline and write DIR/model.onnx, DIR/report.json and DIR/manifest.yaml.
    Compile {
        model: PathBuf,
        /// Pipeline recipe (YAML), e.g. passes/identity.yaml.
        #[arg(long)]
        pipeline: PathBuf,
        /// Output folder (created if missing).
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
        /// Camera blur map (.npy or YAML) for passes that bind the PSF.
        #[arg(long)]
        psf: Option<PathBuf>,
        /// Outputs to keep (comma-separated), instead of recognizing the reconstruction output.
        #[arg(long, value_delimiter = ',')]
        keep_outputs: Option<Vec<String>>,
        /// Calibration frames for pruning and quantization (8/16-bit PNG/TIFF or .npy at the
        /// model's input size); simulated by the physics pipeline when not given.
        #[arg(long)]
        calib: Option<PathBuf>,
        /// Store weights in DIR/model.onnx.data instead of one self-contained file.
        #[arg(long)]
        external_data: bool,
        /// What the deployment needs (YAML: classes, object_px, roi, score_threshold,
        /// max_detections): adds drop-classes / drop-strides / crop-roi before pruning.
        #[arg(long)]
        scene: Option<PathBuf>,
        /// Deployment target: `tract` also checks the model on tract with fixed shapes, writes
        /// an NNEF archive when it loads faster, and DIR/tract.yaml.
        #[arg(long, value_enum, default_value_t)]
        target: crate::targets::Target,
        /// Threads for ONNX Runtime and tract alike (default: every core).
        #[arg(long)]
        threads: Option<usize>,
        /// Print the report as JSON instead of a summary.
        #[arg(long)]
        json: bool,
    },
    /// PSF simulation and the blur-index map.
    Psf {
        #[command(subcommand)]
        command: PsfCommand,
    },
    /// Clean synthetic thermal scenes with YOLO labels (6 M3FD classes), 16-bit PNG.
    Synth {
        out: PathBuf,
        #[arg(long, default_value_t = 16)]
        n: usize,
        /// WIDTHxHEIGHT
        #[arg(long, default_value = "640x480")]
        size: String,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Leave boxes with a side under this many pixels unlabelled.
        #[arg(long, default_value_t = 0.0)]
        min_box: f32,
    },
    /// Single-lens degradation of an image or folder: spatially varying PSF blur, noise, quantization.
    Degrade {
        input: PathBuf,
        output: PathBuf,
        /// PSF set folder (from `psf simulate`).
        #[arg(long)]
        psf: PathBuf,
        /// Quantization step in detector counts (paper: 10 high SNR, 90 low SNR).
        #[arg(long)]
        q: f64,
        /// Noise standard deviation in units of q.
        #[arg(long, default_value_t = 2.0)]
        sigma: f64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        /// Detector full scale in counts (14-bit).
        #[arg(long, default_value_t = crate::optics::degrade::FULL_SCALE_14BIT)]
        full_scale: f64,
    },
    /// A calibration set in one command: clean frames (synthetic, or a real folder rescaled
    /// with its labels) and their degraded copies.
    Dataset {
        out: PathBuf,
        #[arg(long)]
        psf: PathBuf,
        /// Real frames to use instead of synthetic ones (YOLO .txt labels beside them).
        #[arg(long)]
        from: Option<PathBuf>,
        /// COCO JSON labels for --from (FLIR ADAS ships these).
        #[arg(long, requires = "from")]
        coco: Option<PathBuf>,
        #[arg(long, default_value_t = 64)]
        n: usize,
        #[arg(long, default_value = "640x480")]
        size: String,
        #[arg(long, default_value_t = 90.0)]
        q: f64,
        /// Synthetic frames only: leave boxes with a side under this many pixels unlabelled.
        #[arg(long, default_value_t = 0.0)]
        min_box: f32,
        /// Area-downscale clean and degraded frames to WIDTHxHEIGHT after degrading at --size.
        #[arg(long)]
        out_size: Option<String>,
        #[arg(long, default_value_t = 2.0)]
        sigma: f64,
        #[arg(long, default_value_t = 0)]
        seed: u64,
    },
    /// Compile again from a folder's manifest.yaml into a new folder and compare: identical
    /// bytes on the host that built it (exit 1 if not); elsewhere the two models by `verify`.
    Rebuild {
        /// A folder `compile` wrote.
        dir: PathBuf,
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
        /// Frames for the comparison by verify (simulated when not given).
        #[arg(long)]
        data: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Run an artifact on camera frames: OUT/detections.json (COCO results), OUT/labels/*.txt
    /// (YOLO), OUT/images/*.png (boxes drawn), OUT/contact_sheet.png, OUT/run.json (latency per
    /// stage; mAP when YOLO labels lie beside the frames).
    Run {
        /// A folder `compile` or `ship` wrote (model.onnx with tract.yaml or rknn.yaml), or a model file.
        artifact: PathBuf,
        /// A frame, a folder of frames, or a numbered sequence (frames/%05d.png): 8/16-bit
        /// PNG/TIFF or .npy in [0, 1].
        #[arg(long)]
        frames: PathBuf,
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
        /// Engine (default: the artifact's own: tract for a tract target, else ONNX Runtime).
        #[arg(long, value_enum)]
        engine: Option<crate::runtime::Engine>,
        /// Threads (default: the tract target's fastest count, else every core).
        #[arg(long)]
        threads: Option<usize>,
        /// Score threshold (default: an RKNN folder's rknn.yaml, else the scene's
        /// score_threshold, else 0.25).
        #[arg(long)]
        conf: Option<f32>,
        /// NMS IoU threshold (default: an RKNN folder's rknn.yaml, else validation's: 0.6 for
        /// YOLOv5 heads, 0.7 for YOLOv8, so mAP here is verify's).
        #[arg(long)]
        iou: Option<f32>,
        /// Detections kept per frame (default: an RKNN folder's rknn.yaml, else the scene's
        /// max_detections, else 300).
        #[arg(long)]
        max_det: Option<usize>,
        /// Camera blur map, for a model compiled without bind-psf.
        #[arg(long)]
        psf: Option<PathBuf>,
        /// A second artifact run on the same frames: pictures side by side, the boxes only one
        /// of them found in magenta, and this artifact's agreement with it.
        #[arg(long)]
        compare: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
    /// Compare a compiled candidate with its reference on ORT and tract; exit 1 if a gate fails.
    Verify {
        /// The original model (run on ONNX Runtime).
        #[arg(long)]
        reference: PathBuf,
        /// The compiled model (run on ONNX Runtime and tract).
        #[arg(long)]
        candidate: PathBuf,
        /// Folder of frames (PNG/TIFF 8/16-bit grayscale or .npy), YOLO .txt labels beside them.
        #[arg(long, conflicts_with = "random")]
        data: Option<PathBuf>,
        /// Number of synthetic frames when no --data is given.
        #[arg(long, default_value_t = 8)]
        random: usize,
        /// Camera blur map for models that take it as an input.
        #[arg(long)]
        psf: Option<PathBuf>,
        /// Thresholds (YAML, see passes/gate.yaml); without one, nothing can fail.
        #[arg(long)]
        gate: Option<PathBuf>,
        /// Timed runs per model (0: accuracy only, no latency).
        #[arg(long, default_value_t = 20)]
        runs: usize,
        /// Skip the tract run.
        #[arg(long)]
        no_tract: bool,
        /// Threads for ONNX Runtime and tract alike (default: every core).
        #[arg(long)]
        threads: Option<usize>,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long)]
        json: bool,
        /// Also write the gate's checks as JUnit XML (one testcase per check) to this file.
        #[arg(long)]
        junit: Option<PathBuf>,
        /// Gate keys that may go unmeasured (e.g. max_map_drop on frames without labels);
        /// any other unmeasured threshold fails the gate.
        #[arg(long, value_delimiter = ',')]
        allow_unmeasured: Vec<String>,
    },
    /// Compile and measure every variant (unpruned/pruned × f32/fp16/int8 × ORT/tract, and the
    /// original): DIR/bench.md and .json (Pareto front marked), DIR/bench.svg and .png.
    Bench {
        #[command(flatten)]
        on: Variants,
        /// Simulated frames when no --data is given.
        #[arg(long, default_value_t = 4)]
        frames: usize,
        /// Timed runs per model and engine.
        #[arg(long, default_value_t = 10)]
        runs: usize,
        /// Measure the FP16 variants on tract also where tract emulates f16 (x86_64: slow).
        #[arg(long)]
        tract_fp16: bool,
    },
    /// The deployment artifacts of one trained model, measured: DIR/f32 (lossless, tract),
    /// DIR/pruned-f32 (pruned and recovered), DIR/pruned-int8 (tract), DIR/rknn (the NPU's
    /// folder); one table of size, MACs, ORT and tract latency, mAP; DIR/ship.json.
    Ship {
        #[command(flatten)]
        on: Variants,
        /// Simulated frames when no --data is given.
        #[arg(long, default_value_t = 16)]
        frames: usize,
        /// Timed runs per model and engine.
        #[arg(long, default_value_t = 20)]
        runs: usize,
        /// The share of the original's mAP (against labels, else the agreement with its
        /// detections) an artifact must keep to be recommended for a CPU target.
        #[arg(long, default_value_t = 0.9)]
        min_kept: f64,
    },
    /// Candidates against their reference under stressed frames (noise, gain/offset drift,
    /// saturated hot objects, dark/bright scenes, dead/stuck pixels, fixed-pattern noise, a
    /// drifting blur map, NaN pixels): DIR/stress.json, .md, .svg, .png; exit 1 if a gate fails.
    Stress {
        /// The original model (run on ONNX Runtime), e.g. the trained export.
        #[arg(long)]
        reference: PathBuf,
        /// Compiled models to stress (repeat the option for several).
        #[arg(long = "candidate", required = true)]
        candidates: Vec<PathBuf>,
        /// Camera blur map, for models that take it as an input (the reference usually does).
        #[arg(long)]
        psf: Option<PathBuf>,
        /// Base frames (PNG/TIFF/.npy); simulated by the physics pipeline when not given.
        #[arg(long)]
        data: Option<PathBuf>,
        /// Condition file (YAML, see passes/stress.yaml, the default set).
        #[arg(long)]
        conditions: Option<PathBuf>,
        /// Frames per condition (default: the condition file's, else 32).
        #[arg(long)]
        frames: Option<usize>,
        /// Thresholds (YAML: min_agreement, max_rel_l2, max_extra_nonfinite, max_saturation,
        /// max_fp16_headroom, conditions).
        #[arg(long)]
        gate: Option<PathBuf>,
        /// Also write the gate's checks as JUnit XML to this file.
        #[arg(long)]
        junit: Option<PathBuf>,
        /// Gate keys that may go unmeasured (e.g. max_saturation when no candidate is INT8).
        #[arg(long, value_delimiter = ',')]
        allow_unmeasured: Vec<String>,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
        #[arg(long)]
        json: bool,
    },
    /// Build DIR/model.rknn from a `--target rknn` folder with RKNN-Toolkit2 2.5.0 (installed
    /// into the cache on first use), simulate it and compare with ONNX Runtime; exit 1 when an
    /// output or score group falls below --min-cosine or a layer lands on the CPU.
    RknnConvert {
        dir: PathBuf,
        /// Validation frames (PNG/TIFF 8/16-bit grayscale or .npy); simulated when not given.
        #[arg(long)]
        data: Option<PathBuf>,
        #[arg(long, default_value_t = 8)]
        frames: usize,
        #[arg(long, default_value_t = 0.99)]
        min_cosine: f64,
        /// Float model to compare the simulator with instead of DIR/model.onnx (e.g. the model
        /// before rknn-qat trained its weights); same inputs and outputs.
        #[arg(long)]
        reference: Option<PathBuf>,
        #[arg(long)]
        json: bool,
    },
}

/// What `bench` and `ship` both take: one model, its folder of variants, and how to compile
/// and measure them.
#[derive(clap::Args)]
pub struct Variants {
    model: PathBuf,
    #[arg(short = 'o', long = "out")]
    out: PathBuf,
    /// Camera blur map for models that take it as an input.
    #[arg(long)]
    psf: Option<PathBuf>,
    /// Calibration frames for pruning, recovery and quantization; simulated when not given.
    #[arg(long)]
    calib: Option<PathBuf>,
    /// Frames to check and time the variants on (YOLO labels beside them add mAP against
    /// labels); simulated when not given.
    #[arg(long)]
    data: Option<PathBuf>,
    /// Total optimizer steps of the recovery by distillation, shared among the recipe's
    /// recover passes (default: the recipe's); fewer steps train on proportionally fewer of
    /// the recipe's frames, at least 512 or what the steps draw, whichever is less.
    #[arg(long)]
    recover_steps: Option<usize>,
    /// Threads for ONNX Runtime and tract alike (default: every core).
    #[arg(long)]
    threads: Option<usize>,
    #[arg(long)]
    json: bool,
}

#[derive(Subcommand)]
pub enum PsfCommand {
    /// Simulate one PSF per field region from a lens file (scalar diffraction over the band).
    Simulate {
        #[arg(long)]
        lens: PathBuf,
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
        /// Field regions, ROWSxCOLS.
        #[arg(long, default_value = "6x8")]
        grid: String,
        /// Kernel size in pixels (odd).
        #[arg(long, default_value_t = 31)]
        kernel: usize,
    },
    /// Blur-index map from a PSF set: RMS spot radius per region, normalized to [0, 1].
    BlurMap {
        dir: PathBuf,
        /// FILE.npy, FILE.yaml, or FILE without extension for both.
        #[arg(short = 'o', long = "out")]
        out: PathBuf,
    },
}

/// Parses "AxB" into (A, B).
/// `--threads`, or every core; 0 is refused rather than read as "default".
fn threads_or_all(threads: Option<usize>) -> Result<usize> {
    match threads {
        Some(0) => anyhow::bail!("--threads must be at least 1"),
        Some(n) => Ok(n),
        None => Ok(crate::runtime::all_cores()),
    }
}

fn pair(s: &str, what: &str) -> Result<(usize, usize)> {
    let v: Vec<usize> = s.split('x').map(|p| p.trim().parse()).collect::<std::result::Result<_, _>>().map_err(|_| anyhow::anyhow!("{what} '{s}' is not AxB (e.g. 640x480)"))?;
    match v[..] {
        [a, b] if a > 0 && b > 0 && a <= 16384 && b <= 16384 => Ok((a, b)),
        _ => anyhow::bail!("{what} '{s}' is not AxB with sizes in 1..16384"),
    }
}

/// Prints a measured verdict (JSON or its screen) and returns its exit code: 0 when it
/// passed, else `EXIT_GATE_FAILED`.
fn verdict(report: &impl serde::Serialize, json: bool, screen: String, passed: bool) -> Result<u8> {
    if json {
        println!("{}", serde_json::to_string_pretty(report)?);
    } else {
        print!("{screen}");
    }
    Ok(if passed { 0 } else { EXIT_GATE_FAILED })
}

/// Exit code of a run that worked but whose gate failed (bad input exits 2).
pub const EXIT_GATE_FAILED: u8 = 1;

/// Runs the command; returns the exit code (0, or 1 for a failed gate).
pub fn run(cli: Cli) -> Result<u8> {
    match cli.command {
        Command::Inspect { model, json, scene: Some(scene), psf, calib } => {
            let loaded = crate::onnx::load(&model)?;
            let p = crate::pipeline::preview::preview(&loaded.model, &crate::scene::Scene::load(&scene)?, psf, calib)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&p)?);
            } else {
                print!("{}", p.render());
            }
        }
        Command::Inspect { model, json, scene: None, .. } => {
            let loaded = crate::onnx::load(&model)?;
            let mut report = crate::inspect::inspect(&loaded.model)?;
            report.warnings.splice(0..0, loaded.warnings);
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", report.render());
            }
        }
        Command::Profile { models, engine, psf, data, threads, runs, json } => {
            let engines = if engine.is_empty() { vec![crate::runtime::Engine::Ort, crate::runtime::Engine::Tract] } else { engine };
            // One model: its profiles alone (no timing loop to compare against).
            let runs = if models.len() > 1 { runs.max(1) } else { 1 };
            let c = crate::variants::compare(&models, &engines, data.as_deref(), psf.as_deref(), runs, threads_or_all(threads)?)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&c)?);
            } else {
                print!("{}", c.render());
            }
        }
        Command::Compile { model, pipeline, out, psf, keep_outputs, calib, external_data, scene, target, threads, json } => {
            let scene = scene.as_deref().map(crate::scene::Scene::load).transpose()?;
            let req = CompileRequest { model, pipeline, out_dir: out, external_data, context: PassContext { psf, calib, keep_outputs, scene, ..Default::default() }, target, threads: threads_or_all(threads)?, decisions: None, moved: None };
            let r = compile(&req)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!("compiled {} with pipeline '{}' in {:.0} ms -> {}", r.input, r.pipeline.name, r.millis, r.output);
                println!("  nodes {} -> {}, params {} -> {}, MACs {} -> {}", r.before.nodes, r.after.nodes, r.before.params, r.after.params, r.before.macs, r.after.macs);
                for p in &r.passes {
                    println!("  {:<16} {:>8.1} ms  nodes {} -> {}", p.pass, p.millis, p.before.nodes, p.after.nodes);
                }
                if !r.warnings.is_empty() {
                    println!("  {} warning(s), on stderr above and in report.json", r.warnings.len());
                }
            }
        }
        Command::Run { artifact, frames, out, engine, threads, conf, iou, max_det, psf, compare, json } => {
            let options = crate::deploy::Options { engine, threads, conf, iou, max_det, psf };
            let r = crate::run::run(&crate::run::RunRequest { artifact, frames, out, options, compare })?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print!("{}", r.render());
            }
        }
        Command::Rebuild { dir, out, data, json } => {
            if out == dir {
                anyhow::bail!("rebuild writes a new folder to compare with {}: give another -o", dir.display());
            }
            let r = crate::rebuild::rebuild(&crate::rebuild::RebuildRequest { dir, out, data })?;
            return verdict(&r, json, r.render(), r.passed);
        }
        Command::Psf { command } => psf_command(command)?,
        Command::Synth { out, n, size, seed, min_box } => {
            let (w, h) = pair(&size, "--size")?;
            let boxes = crate::dataset::write_synthetic(&out, n, w, h, seed, min_box)?;
            println!("wrote {n} scenes ({boxes} labelled objects) at {w}x{h} to {}", out.display());
        }
        Command::Degrade { input, output, psf, q, sigma, seed, full_scale } => {
            let noise = noise_model(q, sigma, full_scale)?;
            let set = crate::optics::psf_set::PsfSet::load(&psf)?;
            let s = crate::dataset::degrade_path(&input, &output, &set, noise, seed)?;
            println!("degraded {} frame(s), q {q}, sigma {sigma}: PSNR {:.2} dB against clean (blur alone {:.2} dB)", s.frames, s.psnr_db, s.blur_psnr_db);
        }
        Command::Dataset { out, psf, from, coco, n, size, q, min_box, out_size, sigma, seed } => {
            let out_size = out_size.map(|s| pair(&s, "--out-size")).transpose()?;
            let (w, h) = pair(&size, "--size")?;
            let noise = noise_model(q, sigma, crate::optics::degrade::FULL_SCALE_14BIT)?;
            let set = crate::optics::psf_set::PsfSet::load(&psf)?;
            let (shown, staged) = (out.clone(), crate::fsutil::StagedDir::new(&out)?);
            let out = staged.path().to_path_buf();
            let clean = out.join("clean");
            let boxes = match &from {
                Some(dir) => crate::dataset::import_folder(dir, &clean, w, h, coco.as_deref())?,
                None => crate::dataset::write_synthetic(&clean, n, w, h, seed, min_box)?,
            };
            let s = crate::dataset::degrade_path(&clean, &out.join("degraded"), &set, noise, seed)?;
            if let Some((ow, oh)) = out_size {
                crate::dataset::resize_folder(&clean, ow, oh)?;
                crate::dataset::resize_folder(&out.join("degraded"), ow, oh)?;
            }
            let summary = serde_json::json!({ "source": from.as_ref().map_or("synthetic".to_string(), |p| p.display().to_string()), "size": [w, h], "out_size": out_size, "min_box": min_box, "labelled_objects": boxes, "psf": psf.display().to_string(), "degrade": s, "seed": seed });
            crate::fsutil::write_atomic(&out.join("dataset.yaml"), yaml_serde::to_string(&summary)?.as_bytes())?;
            staged.commit()?;
            println!("dataset {}: {} frames, {boxes} objects; degraded PSNR {:.2} dB", shown.display(), s.frames, s.psnr_db);
        }
        Command::Verify { reference, candidate, data, random, psf, gate, runs, no_tract, threads, seed, json, junit, allow_unmeasured } => {
            if gate.is_none() && !allow_unmeasured.is_empty() {
                anyhow::bail!("--allow-unmeasured names checks of a gate; give --gate FILE too");
            }
            let gate = gate.map(|g| crate::verify::gate::Gate::load(&g, allow_unmeasured)).transpose()?;
            if junit.is_some() && gate.is_none() {
                anyhow::bail!("--junit reports the gate's checks; give --gate FILE too (e.g. passes/gate.yaml)");
            }
            let started = std::time::Instant::now();
            let suite = candidate.display().to_string();
            let req = crate::verify::VerifyRequest { reference, candidate, data, random, psf, gate, latency_runs: runs, tract: !no_tract, seed, threads: threads_or_all(threads)? };
            let report = crate::verify::verify(&req)?;
            if let Some(path) = &junit {
                crate::fsutil::write_atomic(path, crate::verify::junit::render(&suite, &report.checks, started.elapsed().as_secs_f64()).as_bytes())?;
            }
            return verdict(&report, json, report.render(), report.passed);
        }
        Command::Bench { on: Variants { model, out, psf, calib, data, recover_steps, threads, json }, frames, runs, tract_fp16 } => {
            let r = crate::bench::bench(&crate::bench::BenchRequest { model, out: out.clone(), psf, calib, data, frames, runs, tract_fp16, recover_steps, threads: threads_or_all(threads)? })?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print!("{}", r.markdown());
                println!("wrote {}", crate::bench::out_files(&out));
            }
        }
        Command::Ship { on: Variants { model, out, psf, calib, data, recover_steps, threads, json }, frames, runs, min_kept } => {
            if runs == 0 || frames == 0 {
                anyhow::bail!("--runs and --frames must be at least 1");
            }
            if !(0.0..=1.0).contains(&min_kept) {
                anyhow::bail!("--min-kept {min_kept} must lie in [0, 1]");
            }
            let r = crate::ship::ship(&crate::ship::ShipRequest { model, out, psf, calib, data, frames, recover_steps, runs, min_kept, threads: threads_or_all(threads)? })?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print!("{}", r.render());
            }
        }
        Command::Stress { reference, candidates, psf, data, conditions, frames, gate, junit, allow_unmeasured, seed, out, json } => {
            if frames.is_some_and(|n| n == 0 || n > 4096) {
                anyhow::bail!("--frames must be in 1..4096");
            }
            if gate.is_none() && !allow_unmeasured.is_empty() {
                anyhow::bail!("--allow-unmeasured names checks of a gate; give --gate FILE too");
            }
            let gate = gate.map(|g| crate::stress::gate::StressGate::load(&g, allow_unmeasured)).transpose()?;
            if junit.is_some() && gate.is_none() {
                anyhow::bail!("--junit reports the gate's checks; give --gate FILE too");
            }
            let r = crate::stress::stress(&crate::stress::StressRequest { reference, candidates, psf, data, conditions, frames, gate, seed })?;
            crate::stress::render::write(&out, &r)?;
            if let Some(path) = &junit {
                crate::fsutil::write_atomic(path, crate::verify::junit::render("stress", &r.checks, r.seconds).as_bytes())?;
            }
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print!("{}", crate::stress::render::markdown(&r));
                println!("\nwrote {}/stress.{{json,md,svg,png}}", out.display());
            }
            if !r.passed {
                return Ok(EXIT_GATE_FAILED);
            }
        }
        Command::RknnConvert { dir, data, frames, min_cosine, reference, json } => {
            let r = crate::targets::rknn_convert::convert(&crate::targets::rknn_convert::ConvertRequest { dir, data, frames, min_cosine, reference })?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                print!("{}", r.render());
            }
            if !r.passed {
                return Ok(EXIT_GATE_FAILED);
            }
        }
    }
    Ok(0)
}

fn noise_model(q: f64, sigma: f64, full_scale: f64) -> Result<crate::optics::degrade::NoiseModel> {
    if !(q > 0.0 && q.is_finite()) || !(sigma >= 0.0 && sigma.is_finite()) || !(full_scale >= 1.0 && full_scale.is_finite()) {
        anyhow::bail!("--q must be > 0, --sigma >= 0 and --full-scale >= 1 (got q {q}, sigma {sigma}, full scale {full_scale})");
    }
    Ok(crate::optics::degrade::NoiseModel { q, sigma, full_scale })
}

fn psf_command(c: PsfCommand) -> Result<()> {
    use crate::optics::{blur_index, lens::Lens, psf, psf_set::PsfSet};
    match c {
        PsfCommand::Simulate { lens, out, grid, kernel } => {
            let lens = Lens::load(&lens)?;
            let (rows, cols) = pair(&grid, "--grid")?;
            if kernel % 2 == 0 || !(3..=127).contains(&kernel) {
                anyhow::bail!("--kernel {kernel} must be odd and in 3..127");
            }
            let t = std::time::Instant::now();
            let (regions, kernels) = psf::simulate(&lens, rows, cols, kernel);
            let set = PsfSet { rows, cols, k: kernel, kernels };
            set.save(&out, &lens, &regions)?;
            let st = set.stats();
            let (lo, hi) = st.iter().fold((f64::MAX, f64::MIN), |(a, b), s| (a.min(s.rms_radius), b.max(s.rms_radius)));
            println!("{} PSFs ({rows}x{cols}, {kernel}x{kernel}) for '{}' in {:.2} s -> {}; RMS spot radius {lo:.2}-{hi:.2} px", rows * cols, lens.name, t.elapsed().as_secs_f64(), out.display());
        }
        PsfCommand::BlurMap { dir, out } => {
            let set = PsfSet::load(&dir)?;
            let map = blur_index::blur_map(&set.stats(), set.rows, set.cols);
            let ext = out.extension().and_then(|e| e.to_str()).map(str::to_string);
            let npy = || crate::fsutil::write_atomic(&out.with_extension("npy"), &crate::optics::npy::to_bytes(&[map.rows, map.cols], &map.values));
            let yaml = || crate::fsutil::write_atomic(&out.with_extension("yaml"), map.to_yaml().as_bytes());
            match ext.as_deref() {
                Some("npy") => npy()?,
                Some("yaml" | "yml") => yaml()?,
                None => { npy()?; yaml()?; }
                Some(e) => anyhow::bail!("blur map files are .npy or .yaml, not .{e}"),
            }
            println!("blur map {}x{} -> {}", map.rows, map.cols, out.display());
        }
    }
    Ok(())
}
