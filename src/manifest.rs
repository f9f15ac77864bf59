//! `manifest.yaml`: what made an output folder, complete enough to rebuild it. The input and
//! every file the compile read (blur map, calibration frames) by path and hash; the recipe
//! with every option resolved; the scene; the target and thread counts; the tool's, ONNX
//! Runtime's, tract's and torch's versions; the host that built it; every training's device,
//! threads and steps; and whether a rebuild can give the same bytes.

use crate::pipeline::Recipe;
use anyhow::{Context, Result};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::path::Path;

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct Manifest {
    pub tool: String,
    pub tool_version: String,
    pub input: String,
    pub input_sha256: String,
    pub model: String,
    pub model_sha256: String,
    /// The recipe as it ran: scene passes placed, every option resolved.
    pub pipeline: Recipe,
    pub pipeline_file: String,
    pub inputs: Inputs,
    pub target: crate::targets::Target,
    /// Threads of the target check's timed runs.
    pub threads: usize,
    pub external_data: bool,
    pub host: Host,
    pub versions: Versions,
    /// Each training run: pass, device, threads, steps taken of those planned.
    #[serde(default)]
    pub training: Vec<crate::torch::train::Account>,
    /// True when the same input, recipe, threads and host give the same bytes.
    pub reproducible: bool,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub not_reproducible: Vec<String>,
    #[serde(default)]
    pub passes: Vec<serde_json::Value>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub target_check: Option<serde_json::Value>,
}

/// What the command line supplied, by path and content hash.
#[derive(Serialize, Deserialize, Debug, Clone, Default)]
pub struct Inputs {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub psf: Option<Hashed>,
    /// Calibration frames (`--calib`); absent: frames simulated by the physics pipeline
    /// (deterministic in the passes' seeds).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub calib: Option<Hashed>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub keep_outputs: Option<Vec<String>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<crate::scene::Scene>,
}

#[derive(Serialize, Deserialize, Debug, Clone, PartialEq)]
pub struct Hashed {
    pub path: String,
    pub sha256: String,
    /// Files hashed (a folder's frames), 1 for a file.
    pub files: usize,
}

impl Hashed {
    /// A file's hash, or a folder's: every file in it, by name and content, in name order.
    pub fn of(path: &Path) -> Result<Hashed> {
        let mut h = Sha256::new();
        let files = if path.is_dir() {
            let mut names: Vec<_> = std::fs::read_dir(path).with_context(|| format!("cannot read {}", path.display()))?.flatten().filter(|e| e.path().is_file()).map(|e| e.path()).collect();
            names.sort();
            for f in &names {
                h.update(f.file_name().map(|n| n.as_encoded_bytes()).unwrap_or_default());
                h.update([0]);
                h.update(std::fs::read(f).with_context(|| format!("cannot read {}", f.display()))?);
            }
            names.len()
        } else {
            h.update(std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?);
            1
        };
        Ok(Hashed { path: path.display().to_string(), sha256: hex(&h.finalize()), files })
    }
}

/// The machine: what decides whether a rebuild can give the same bytes.
#[derive(Serialize, Deserialize, Debug, Clone, PartialEq)]
pub struct Host {
    pub cpu: String,
    pub cores: usize,
    pub arch: String,
    pub os: String,
}

impl Host {
    pub fn this() -> Host {
        let cpu = std::fs::read_to_string("/proc/cpuinfo").ok().and_then(|t| t.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).map(|s| s.trim().to_string())).unwrap_or_else(|| "unknown".into());
        Host { cpu, cores: std::thread::available_parallelism().map_or(1, |n| n.get()), arch: std::env::consts::ARCH.into(), os: std::env::consts::OS.into() }
    }
}

/// The tract this build links (Cargo.toml pins it exactly).
const TRACT_VERSION: &str = "0.23.9";

#[derive(Serialize, Deserialize, Debug, Clone)]
pub struct Versions {
    pub onnxruntime: String,
    pub tract: String,
    /// The torch that trained, when a pass trained.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub torch: Option<String>,
}

impl Versions {
    pub fn of(training: &[crate::torch::train::Account]) -> Versions {
        Versions {
            onnxruntime: crate::runtime::ort_lib::ORT_VERSION.into(),
            tract: TRACT_VERSION.into(),
            torch: training.first().map(|t| t.torch.clone()),
        }
    }
}

pub fn load(dir: &Path) -> Result<Manifest> {
    let path = dir.join("manifest.yaml");
    let text = std::fs::read_to_string(&path).with_context(|| format!("cannot read {}: is {} a folder `compile` wrote?", path.display(), dir.display()))?;
    yaml_serde::from_str(&text).map_err(|e| anyhow::anyhow!("{}: not a pdi-compile manifest: {e}", path.display()))
}

pub fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

pub fn sha256_file(path: &Path) -> Result<String> {
    Ok(hex(&Sha256::digest(std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?)))
}
