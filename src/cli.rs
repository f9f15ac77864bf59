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
        /// Store weights in DIR/model.onnx.data instead of one self-contained file.
        #[arg(long)]
        external_data: bool,
        /// Print the report as JSON instead of a summary.
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
        /// Timed runs per model.
        #[arg(long, default_value_t = 20)]
        runs: usize,
        /// Skip the tract run.
        #[arg(long)]
        no_tract: bool,
        #[arg(long, default_value_t = 0)]
        seed: u64,
        #[arg(long)]
        json: bool,
    },
}

/// Exit code of a run that worked but whose gate failed (bad input exits 2).
pub const EXIT_GATE_FAILED: u8 = 1;

/// Runs the command; returns the exit code (0, or 1 for a failed gate).
pub fn run(cli: Cli) -> Result<u8> {
    match cli.command {
        Command::Inspect { model, json } => {
            let loaded = crate::onnx::load(&model)?;
            let mut report = crate::inspect::inspect(&loaded.model)?;
            report.warnings.splice(0..0, loaded.warnings);
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", report.render());
            }
        }
        Command::Compile { model, pipeline, out, psf, keep_outputs, external_data, json } => {
            let req = CompileRequest { model, pipeline, out_dir: out, external_data, context: PassContext { psf, calib: None, keep_outputs } };
            let r = compile(&req)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&r)?);
            } else {
                println!("compiled {} with pipeline '{}' in {:.0} ms -> {}", r.input, r.pipeline.name, r.millis, r.output);
                println!("  nodes {} -> {}, params {} -> {}, MACs {} -> {}", r.before.nodes, r.after.nodes, r.before.params, r.after.params, r.before.macs, r.after.macs);
                for p in &r.passes {
                    println!("  {:<16} {:>8.1} ms  nodes {} -> {}", p.pass, p.millis, p.before.nodes, p.after.nodes);
                }
                for w in &r.warnings {
                    println!("  warning: {w}");
                }
            }
        }
        Command::Verify { reference, candidate, data, random, psf, gate, runs, no_tract, seed, json } => {
            let gate = gate.map(|g| crate::verify::gate::Gate::load(&g)).transpose()?;
            let req = crate::verify::VerifyRequest { reference, candidate, data, random, psf, gate, latency_runs: runs, tract: !no_tract, seed };
            let report = crate::verify::verify(&req)?;
            if json {
                println!("{}", serde_json::to_string_pretty(&report)?);
            } else {
                print!("{}", report.render());
            }
            if !report.passed {
                return Ok(EXIT_GATE_FAILED);
            }
        }
    }
    Ok(0)
}
