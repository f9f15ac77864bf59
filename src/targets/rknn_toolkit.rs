//! RKNN-Toolkit2, the leaf the RKNN target's files share: the 8-bit pixel grid the NPU is
//! fed, and the one way to run the toolkit worker (`rknn_worker.py`, in the toolkit's venv),
//! through the protocol of the torch workers (`pyenv::run_python`: the worker turn, JSON
//! events on stdout, its `done` event the result).

use anyhow::Result;
use std::path::Path;

/// The NPU is fed 8-bit pixels; the model sees them divided by this.
pub const PIXEL_SCALE: f32 = 255.0;

const WORKER: &str = include_str!("rknn_worker.py");

/// A [0, 1] frame as the model sees it on the NPU: its 8-bit pixels divided by 255.
pub fn npu_input(v: &[f32]) -> Vec<f32> {
    pixels(v).into_iter().map(|p| p / PIXEL_SCALE).collect()
}

/// A [0, 1] frame as the 8-bit pixel values the NPU is fed (rounded: the camera delivers
/// integers, and the reference run gets exactly these values divided by 255).
pub fn pixels(v: &[f32]) -> Vec<f32> {
    v.iter().map(|&x| (x.clamp(0.0, 1.0) * PIXEL_SCALE).round()).collect()
}

/// Runs the toolkit worker on `job` in `work` (where the toolkit leaves its own dumps); what
/// the toolkit prints goes to `log` when given. Returns the worker's result, or its failure
/// with the last line it wrote on stderr.
pub fn run(work: &Path, job: &serde_json::Value, log: Option<&Path>) -> Result<serde_json::Value> {
    let python = crate::pyenv::toolkit_python()?;
    std::fs::write(work.join("rknn_worker.py"), WORKER)?;
    let job_path = work.join("job.json");
    std::fs::write(&job_path, serde_json::to_vec(job)?)?;
    crate::pyenv::run_python(&python, work, "rknn_worker.py", &[job_path.as_os_str()], 1, log, |_| {})
}
