//! pdi-compile: a model compiler and deployment toolchain for PDI-Net.
//!
//! Layers, lowest first. A module imports from its own layer or below, no two modules import
//! each other (directly or through others), and only the pipeline and the commands import
//! `passes`; `tests/suite/layers.rs` checks this map against the code:
//! 1. `tensor`, `fsutil`, `warn`, `canvas`, `clock`: values, atomic files, warnings, drawing,
//!    a pass's time by phase;
//! 2. `onnx` (schema, I/O, edits), `ir` (graph index, shapes, costs, and the rewrites several
//!    layers share: `ir::rewrite`);
//! 3. `analysis` (PDI-Net's parts), `metrics` (tensor error, mAP, validation's decode and
//!    agreement), `detect` (decode, NMS, split heads), `optics` (PSFs, blur maps, degradation,
//!    stress conditions), `inspect` (and the node/parameter/MAC counts every pass reports);
//! 4. `runtime` (ONNX Runtime and tract, interleaved latency), `frames`, `dataset`,
//!    `calib_frames`, `pyenv` (the cache's Python environments), `torch` (the PyTorch workers:
//!    interpreter, trainer, op check, learned rounding);
//! 5. analyses and rewrites: `prune`, `quant`, `scene`, `targets`;
//! 6. `passes` (the pass contract and context, the registry, one pass per file);
//! 7. `pipeline` (recipes, the whole-recipe check, the runner, `inspect --scene`'s preview);
//! 8. shared by the commands: `deploy` (running an artifact: `deploy::Detector`), `verify`
//!    (comparing two models), `manifest`;
//! 9. commands: `compile`, `rebuild`, `run`, `ship`, `bench`, `stress`, `cli`, `fuzz_targets`,
//!    `reference` (the generated docs/reference/).

pub mod analysis;
pub mod bench;
pub mod calib_frames;
pub mod canvas;
pub mod clock;
pub mod cli;
pub mod compile;
pub mod dataset;
pub mod deploy;
pub mod detect;
pub mod metrics;
pub mod frames;
pub mod fuzz_targets;
pub mod fsutil;
pub mod inspect;
pub mod manifest;
pub mod ir;
pub mod onnx;
pub mod optics;
pub mod passes;
pub mod pipeline;
pub mod pyenv;
pub mod torch;
pub mod quant;
pub mod rebuild;
pub mod reference;
pub mod ridge;
pub mod run;
pub mod prune;
pub mod runtime;
pub mod scene;
pub mod ship;
pub mod stress;
pub mod targets;
pub mod variants;
pub mod tensor;
pub mod verify;
pub mod warn;
