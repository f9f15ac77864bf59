//! The PyTorch side, in one place: the ONNX interpreter over torch (`interpreter.py`), the
//! distillation trainer that `recover`, QAT and `rknn-qat` run (`trainer.py`, under torchrun
//! for several processes), the op check (`opcheck.py`) and learned rounding (`rounding.py`).
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

/// The scripts, by file name; they import each other from the folder they are written to.
pub const SCRIPTS: &[(&str, &str)] = &[
    ("interpreter.py", include_str!("interpreter.py")),
    ("trainer.py", include_str!("trainer.py")),
    ("opcheck.py", include_str!("opcheck.py")),
    ("rounding.py", include_str!("rounding.py")),
];

/// Writes the scripts into `dir` and runs `script` with `args` as `ranks` processes (see
/// `pyenv::run_worker`): its `done` event, after `on_event` saw the others.
pub fn run(dir: &Path, script: &str, args: &[&OsStr], ranks: usize, on_event: impl FnMut(&serde_json::Value)) -> Result<serde_json::Value> {
    for (name, source) in SCRIPTS {
        std::fs::write(dir.join(name), source)?;
    }
    crate::pyenv::run_worker(dir, script, args, ranks, on_event)
}
