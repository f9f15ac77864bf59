//! Runtimes behind one small interface: run a model on named inputs, get named outputs.
//!
//! Any intermediate value can be observed by asking for it as an extra output
//! ([`crate::onnx::edit::expose_outputs`] rewrites the model before the session is built).

pub mod engine_gap;
pub mod latency;
pub mod op_profile;
pub mod ort_lib;
pub mod ort_profile;
pub mod ort_runtime;
pub mod tract_runtime;

use crate::onnx::proto::ModelProto;
use crate::tensor::Tensor;
use anyhow::Result;

pub type NamedTensors = Vec<(String, Tensor)>;

pub trait Runtime {
    /// Short name for reports ("ort", "tract").
    fn name(&self) -> &'static str;
    /// Runs once; outputs come back in the model's output order.
    fn run(&mut self, inputs: &[(String, Tensor)]) -> Result<NamedTensors>;
}

/// Which engine to build a [`Runtime`] with.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Engine {
    Ort,
    Tract,
}

impl Engine {
    /// The name reports and tables use (as serialized).
    pub fn as_str(self) -> &'static str {
        match self {
            Engine::Ort => "ort",
            Engine::Tract => "tract",
        }
    }
}

/// Builds a session for `model` on `threads` threads; `inputs` fixes the shapes for engines
/// that want them up front. Wherever engines are compared they get the same thread count.
pub fn load(engine: Engine, model: &ModelProto, inputs: &[(String, Tensor)], threads: usize) -> Result<Box<dyn Runtime>> {
    Ok(match engine {
        Engine::Ort => Box::new(ort_runtime::OrtRuntime::with_options(model, ort::session::builder::GraphOptimizationLevel::Level3, threads)?),
        Engine::Tract => Box::new(tract_runtime::TractRuntime::new(model, inputs, threads)?),
    })
}

/// The default thread count for timed runs: every core the process may use.
pub fn all_cores() -> usize {
    std::thread::available_parallelism().map_or(1, |n| n.get())
}
