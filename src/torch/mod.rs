//! The PyTorch side, in one place: the ONNX interpreter over torch (`interpreter.py`), the
//! distillation trainer that `recover`, QAT and `rknn-qat` run (`trainer.py`, under torchrun
//! for several processes; `pseudo.py` adds the detector's own loss on the teacher's
//! detections, from the training code in `models/pdinet`), the op check (`opcheck.py`) and
//! learned rounding (`rounding.py`).
//! Every job writes all of them into its scratch folder and starts one through
//! `pyenv::run_worker`'s protocol (JSON events on stdout, the last stderr line on failure).
//! The Rust half: the shared schedule (`schedule`), the specs of what a training matches
//! (`heads`), and the client that runs a training and takes its weights back (`train`).

pub mod crops;
pub mod heads;
pub mod schedule;
pub mod train;

use anyhow::Result;
use std::ffi::OsStr;
use std::path::Path;

/// The scripts, by path; they import each other from the folder they are written to. YOLOv8's
/// loss is the one the shipped models trained with, taken from where they were trained.
pub const SCRIPTS: &[(&str, &str)] = &[
    ("interpreter.py", include_str!("interpreter.py")),
    ("trainer.py", include_str!("trainer.py")),
    ("pseudo.py", include_str!("pseudo.py")),
    ("opcheck.py", include_str!("opcheck.py")),
    ("rounding.py", include_str!("rounding.py")),
    ("pdinet/__init__.py", ""),
    ("pdinet/boxes.py", include_str!("../../models/pdinet/boxes.py")),
    ("pdinet/loss_v8.py", include_str!("../../models/pdinet/loss_v8.py")),
    ("pdinet/model.py", include_str!("../../models/pdinet/model.py")),
];

/// Writes the scripts into `dir`, where they import each other.
pub fn write_scripts(dir: &Path) -> Result<()> {
    for (name, source) in SCRIPTS {
        let path = dir.join(name);
        if let Some(parent) = path.parent() {
            std::fs::create_dir_all(parent)?;
        }
        std::fs::write(path, source)?;
    }
    Ok(())
}

/// Writes the scripts into `dir` and runs `script` with `args` as `ranks` processes (see
/// `pyenv::run_worker`): its `done` event, after `on_event` saw the others.
pub fn run(dir: &Path, script: &str, args: &[&OsStr], ranks: usize, on_event: impl FnMut(&serde_json::Value)) -> Result<serde_json::Value> {
    write_scripts(dir)?;
    crate::pyenv::run_worker(dir, script, args, ranks, on_event)
}
