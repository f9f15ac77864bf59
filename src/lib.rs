//! pdi-compile: a model compiler and deployment toolchain for PDI-Net.
//!
//! Layers, lowest first (a module imports from its own layer or below; the imports that still
//! point up are listed, to be removed, in `tests/suite/layers.rs`, which checks this map):
//! 1. `tensor`, `fsutil`, `warn`, `canvas`: values, atomic files, warnings, drawing;
//! 2. `onnx` (schema, I/O, edits), `ir` (graph index, shapes, costs);
//! 3. `analysis` (PDI-Net's parts), `metrics`, `detect` (decode, NMS, split heads), `optics`
//!    (PSFs, blur maps, degradation), `inspect`;
//! 4. `runtime` (ONNX Runtime and tract), `frames`, `dataset`, `calib_frames`, `pyenv`;
//! 5. analyses and rewrites: `prune`, `quant`, `scene`, `targets`;
//! 6. `passes` (one pass per file); 7. `pipeline` (recipes, the pass registry);
//! 8. shared by the commands: `deploy` (running an artifact: `deploy::Detector`), `verify`
//!    (comparing two models), `manifest`;
//! 9. commands: `compile`, `rebuild`, `run`, `ship`, `bench`, `stress`, `cli`, `fuzz_targets`,
//!    `reference` (the generated docs/reference/).

pub mod analysis;
pub mod bench;
pub mod calib_frames;
pub mod canvas;
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
pub mod quant;
pub mod rebuild;
pub mod reference;
pub mod run;
pub mod prune;
pub mod runtime;
pub mod scene;
pub mod ship;
pub mod stress;
pub mod targets;
pub mod tensor;
pub mod verify;
pub mod warn;
