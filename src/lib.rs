//! pdi-compile: a model compiler and deployment toolchain for PDI-Net.
//!
//! Module map: `onnx` (schema, I/O), `ir` (graph index, shapes, costs), `analysis`
//! (recognizing PDI-Net's parts), `pipeline` (passes and recipes), `runtime` (ONNX Runtime
//! and tract behind one interface), `inspect` and `compile` (the commands), `targets` (what
//! ships for tract and the RK3588 NPU), `bench` (run time against error), `cli`.

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
