//! What an artifact is and how it wants to be run: a folder `compile` wrote (tract target:
//! tract on its fastest thread count; RKNN target: its ONNX, split head and all, on ONNX
//! Runtime, as the board's `run_rknn.py` decodes it; otherwise ONNX Runtime), one of `ship`'s
//! variant folders (the same), or a bare model file (ONNX Runtime).

use crate::runtime::Engine;
use anyhow::{bail, Result};
use std::path::{Path, PathBuf};

#[derive(Clone, Debug, serde::Serialize)]
pub struct Artifact {
    /// The ONNX file that runs.
    pub model: PathBuf,
    /// The engine the artifact was built for, and why in a few words.
    pub engine: Engine,
    pub why: String,
    /// The thread count its build found fastest (tract target only).
    pub threads: Option<usize>,
    /// Post-processing the artifact prescribes (the RKNN target's rknn.yaml): score
    /// threshold, NMS IoU, detections per frame.
    pub post: Option<(f32, f32, usize)>,
}

/// What `tract.yaml` says about running the model (the rest is for people).
#[derive(serde::Deserialize)]
struct TractYaml {
    fastest_threads: usize,
}

/// What `rknn.yaml` says about post-processing (what run_rknn.py applies on the board).
#[derive(serde::Deserialize)]
struct RknnYaml {
    post_processing: crate::targets::rknn::PostProcessing,
}

impl Artifact {
    pub fn open(path: &Path) -> Result<Artifact> {
        if path.is_file() {
            return Ok(Artifact { model: path.to_path_buf(), engine: Engine::Ort, why: "a model file: ONNX Runtime".into(), threads: None, post: None });
        }
        if !path.is_dir() {
            bail!("{}: no such artifact (a folder compile or ship wrote, or a model file)", path.display());
        }
        if path.join("ship.json").is_file() {
            let mut variants: Vec<String> = std::fs::read_dir(path)?
                .filter_map(|e| e.ok())
                .filter(|e| e.path().join("model.onnx").is_file())
                .map(|e| e.file_name().to_string_lossy().into_owned())
                .collect();
            variants.sort();
            bail!("{} is a ship folder with several artifacts: give one of its variants ({})", path.display(), variants.join(", "));
        }
        let model = path.join("model.onnx");
        if !model.is_file() {
            bail!("{}: no model.onnx (a folder compile or ship wrote holds one)", path.display());
        }
        let tract = path.join("tract.yaml");
        if tract.is_file() {
            let text = std::fs::read_to_string(&tract)?;
            let t: TractYaml = yaml_serde::from_str(&text).map_err(|e| anyhow::anyhow!("{}: {e}", tract.display()))?;
            return Ok(Artifact { model, engine: Engine::Tract, why: format!("compiled for tract (tract.yaml: fastest on {} thread(s))", t.fastest_threads), threads: Some(t.fastest_threads.max(1)), post: None });
        }
        let rknn = path.join("rknn.yaml");
        if rknn.is_file() {
            let r: RknnYaml = yaml_serde::from_str(&std::fs::read_to_string(&rknn)?).map_err(|e| anyhow::anyhow!("{}: {e}", rknn.display()))?;
            let p = r.post_processing;
            let why = "the RK3588 build's ONNX on ONNX Runtime, post-processed as rknn.yaml says (run_rknn.py runs model.rknn on the board)".into();
            return Ok(Artifact { model, engine: Engine::Ort, why, threads: None, post: Some((p.score_threshold, p.nms_iou, p.max_detections)) });
        }
        Ok(Artifact { model, engine: Engine::Ort, why: "compiled for ONNX Runtime".into(), threads: None, post: None })
    }
}
