//! `--target tract`: the compiled model, proven to load and run on tract with fixed shapes.
//!
//! Writes DIR/tract.yaml: the input shape tract was fixed to, load and run times (ONNX and
//! NNEF), tract's agreement with ONNX Runtime on a simulated camera frame, and which file to
//! load. DIR/model.nnef.tar is kept only when it loads faster than the ONNX file (measured:
//! it skips ONNX parsing, type inference and decluttering).
//!
//! Depthwise convolutions wider than tract's SIMD kernel takes are split into bands in the
//! shipped model (`split-wide-depthwise`), so any tract that loads it runs them vectorized;
//! convolutions that ran faster on tract as matrix products over column tiles than as its
//! direct spatial convolution ship tiled (`tract_tiles`). tract.yaml lists both, and ONNX
//! Runtime, timed for scale, runs the model without them.
//!
//! tract.yaml also says whether one thread ran the model faster than all of them, each run
//! after a pause as between camera frames (`fastest_threads`): on small models, waking
//! tract's sleeping workers for every operator costs more than the second core gives.
//!
//! An INT8 model is kept only where tract ran it faster than the float model it was quantized
//! from, on the machine that compiles: tract's integer kernels do not beat its f32 ones
//! everywhere (the trained tiny v5 pruned, 256x192, 2 x86 cores: 22.3 ms in INT8 against
//! 11.7 ms in f32), and a deployment should not pay INT8's error for nothing. tract.yaml says
//! which and why.

use crate::calib_frames::calibration_frames;
use crate::fsutil::write_atomic;
use crate::metrics::tensor_error::compare;
use crate::onnx::proto::ModelProto;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::tract_runtime::{typed_model, TractRuntime};
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use crate::runtime::latency::interleaved;
use anyhow::{anyhow, bail, Result};
use std::path::Path;
use std::time::Instant;
use tract_onnx::prelude::Framework;
use tract_onnx::WithOnnx;

/// Timed runs per loaded model (the median is reported).
const RUNS: usize = 5;
/// Runs per thread count when one thread is weighed against all of them.
const THREAD_RUNS: usize = 7;
/// One thread is recommended only when this much faster: medians of one model timed against
/// itself this way differ by a few percent.
const THREADS_MIN_GAIN: f64 = 0.05;

#[derive(serde::Serialize)]
pub struct TractArtifact {
    pub load: &'static str,
    pub input: String,
    pub shape: Vec<usize>,
    pub onnx_load_ms: f64,
    pub onnx_run_ms: f64,
    pub nnef_load_ms: Option<f64>,
    pub nnef_run_ms: Option<f64>,
    pub nnef: String,
    /// Worst output rel L2 of tract against ONNX Runtime on the same frame.
    pub rel_l2_vs_ort: f64,
    /// ONNX Runtime's median on the same frame and threads, for scale.
    pub ort_run_ms: f64,
    pub threads: usize,
    /// For a quantized model: INT8 kept or replaced by its float model, with both timings.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub int8: Option<String>,
    /// Depthwise convolutions split into bands for tract's SIMD kernel, and those left whole.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub depthwise_split: Vec<serde_json::Value>,
    /// Convolutions tract would run directly, timed alone whole and in column tiles.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub conv_tiles: Vec<super::tract_tiles::ConvForm>,
    /// tract's median on one thread and on `threads`, each run after a pause (see
    /// `time_threads`); absent when `threads` is 1.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub one_thread_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub all_threads_ms: Option<f64>,
    /// The thread count to run this model with: 1 where one thread ran it faster that way.
    pub fastest_threads: usize,
}

/// The choices the tract target makes by timing, as an earlier build recorded them in its
/// tract.yaml: a rebuild applies them instead of timing again (as TensorRT reuses its timing
/// cache), so that it gives the same bytes however loaded the machine is.
#[derive(Clone, Debug, Default)]
pub struct Decisions {
    /// INT8 kept (true) or replaced by its float model (false).
    pub int8: Option<bool>,
    /// The convolutions that ship tiled.
    pub tiled: Vec<String>,
    /// The NNEF archive kept.
    pub nnef: bool,
}

impl Decisions {
    /// From a tract.yaml's contents (the manifest's `target_check`).
    pub fn recorded(artifact: &serde_json::Value) -> Decisions {
        Decisions {
            int8: artifact["int8"].as_str().map(|s| s.starts_with("kept")),
            tiled: artifact["conv_tiles"].as_array().into_iter().flatten().filter(|f| f["tiled"] == true).filter_map(|f| f["node"].as_str().map(String::from)).collect(),
            nnef: artifact["load"] == "model.nnef.tar",
        }
    }
}

/// Checks `model` on tract and writes DIR/tract.yaml (and the NNEF archive where it pays);
/// returns the model to ship: `model`, or `float` (the model before quantization) where
/// tract ran that faster.
/// With `reuse`, the timed choices are an earlier build's.
pub fn write(dir: &Path, model: ModelProto, float: Option<ModelProto>, threads: usize, reuse: Option<&Decisions>) -> Result<(TractArtifact, ModelProto)> {
    let feeds = fixed_inputs(&model)?;
    let (name, frame) = feeds[0].clone();
    let (model, int8) = match float.filter(|_| is_quantized(&model)) {
        None => (model, None),
        Some(float) if reuse.is_some_and(|r| r.int8.is_some()) => match reuse.and_then(|r| r.int8) {
            Some(false) => (float, Some("replaced by its float model, as the build this one repeats decided by timing".to_string())),
            _ => (model, Some("kept: INT8, as the build this one repeats decided by timing".to_string())),
        },
        Some(float) => {
            let (_, q_ms) = timed_runs(&mut TractRuntime::new(&model, &feeds, threads)?, &feeds)?;
            let (_, f_ms) = timed_runs(&mut TractRuntime::new(&float, &feeds, threads)?, &feeds)?;
            if q_ms < f_ms {
                (model, Some(format!("kept: INT8 ran in {q_ms:.2} ms, its float model in {f_ms:.2} ms on this machine ({threads} threads)")))
            } else {
                let why = format!("replaced by its float model: INT8 ran in {q_ms:.2} ms, the float model in {f_ms:.2} ms on this machine ({threads} threads), so INT8 would cost accuracy for no speed");
                crate::warn::warn(format!("tract target: {why}"));
                (float, Some(why))
            }
        }
    };
    let for_ort = model.clone();
    let mut model = model;
    let (split, left) = crate::runtime::tract_runtime::make_tract_ready(model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?)?;
    let conv_tiles = match reuse {
        Some(r) => super::tract_tiles::apply(&mut model, &r.tiled)?,
        None => super::tract_tiles::choose(&mut model, threads)?,
    };
    let model = &model;

    let t = Instant::now();
    let mut from_onnx = TractRuntime::new(model, &feeds, threads)?;
    let onnx_load_ms = t.elapsed().as_secs_f64() * 1e3;
    let (tract_out, onnx_run_ms) = timed_runs(&mut from_onnx, &feeds)?;
    let (one_thread_ms, all_threads_ms) = if threads > 1 { time_threads(model, &mut from_onnx, &feeds).map(|(a, b)| (Some(a), Some(b)))? } else { (None, None) };
    // Advice for whoever runs the artifact, not a fault of the model: tract.yaml, no warning.
    let fastest_threads = match (one_thread_ms, all_threads_ms) {
        (Some(one), Some(all)) if one < all * (1.0 - THREADS_MIN_GAIN) => 1,
        _ => threads,
    };
    let mut ort = OrtRuntime::with_options(&for_ort, ort::session::builder::GraphOptimizationLevel::Level3, threads)?;
    let (ort_out, ort_run_ms) = timed_runs(&mut ort, &feeds)?;
    let rel_l2_vs_ort = tract_out.iter().zip(&ort_out).map(|((_, a), (_, b))| compare(&b.data.to_f64(), &a.data.to_f64()).rel_l2).fold(0.0, f64::max);

    let tar = dir.join("model.nnef.tar");
    let (mut nnef_load_ms, mut nnef_run_ms) = (None, None);
    let nnef = match write_nnef(model, &feeds, &tar) {
        Err(e) => format!("not written: {e:#}"),
        Ok(()) => {
            let outputs: Vec<String> = model.graph.iter().flat_map(|g| &g.output).map(|o| o.name.clone()).collect();
            let t = Instant::now();
            let typed = nnef().model_for_path(&tar).map_err(|e| anyhow!("tract cannot read its NNEF archive: {e:#}"))?;
            let mut from_nnef = TractRuntime::from_typed(typed, vec![name.clone()], outputs, threads)?;
            let load = t.elapsed().as_secs_f64() * 1e3;
            let (nnef_out, run) = timed_runs(&mut from_nnef, &feeds)?;
            let drift = tract_out.iter().zip(&nnef_out).map(|((_, a), (_, b))| compare(&a.data.to_f64(), &b.data.to_f64()).rel_l2).fold(0.0, f64::max);
            (nnef_load_ms, nnef_run_ms) = (Some(load), Some(run));
            if drift > 1e-6 {
                let _ = std::fs::remove_file(&tar);
                format!("removed: its outputs differ from the ONNX file's on tract (rel L2 {drift:.2e})")
            } else if let Some(r) = reuse {
                if !r.nnef {
                    let _ = std::fs::remove_file(&tar);
                }
                format!("{}: as the build this one repeats decided by timing (loads in {load:.0} ms against {onnx_load_ms:.0} ms from ONNX now)", if r.nnef { "kept" } else { "removed" })
            } else if load < onnx_load_ms {
                format!("kept: loads in {load:.0} ms against {onnx_load_ms:.0} ms from ONNX")
            } else {
                let _ = std::fs::remove_file(&tar);
                format!("removed: loads in {load:.0} ms, no faster than {onnx_load_ms:.0} ms from ONNX")
            }
        }
    };
    let artifact = TractArtifact {
        load: if tar.exists() { "model.nnef.tar" } else { "model.onnx" },
        input: name,
        shape: frame.shape.clone(),
        onnx_load_ms,
        onnx_run_ms,
        nnef_load_ms,
        nnef_run_ms,
        nnef,
        rel_l2_vs_ort,
        ort_run_ms,
        threads,
        int8,
        depthwise_split: split.into_iter().chain(left).collect(),
        conv_tiles,
        one_thread_ms,
        all_threads_ms,
        fastest_threads,
    };
    write_atomic(&dir.join("tract.yaml"), yaml_serde::to_string(&artifact)?.as_bytes())?;
    Ok((artifact, model.clone()))
}

/// tract's median latency on one thread and on `all` (the target's own runtime, on every
/// thread it was given), interleaved, every run after the pause `runtime::latency::interleaved`
/// takes: frames from a camera come with gaps, and after one tract's rayon workers have gone
/// to sleep and each parallel operator pays to wake them.
/// Measured on the trained tiny v5 at 256x192, 2 cores: 10.4 ms on 2 threads back to back,
/// 15.6 ms on 2 threads with a 60 ms pause before each run, 12.7 ms on one thread either way.
fn time_threads(model: &ModelProto, all: &mut TractRuntime, feeds: &[(String, Tensor)]) -> Result<(f64, f64)> {
    let mut one = TractRuntime::new(model, feeds, 1)?;
    let lat = interleaved(&mut [("one".into(), &mut one, feeds.to_vec()), ("all".into(), all, feeds.to_vec())], THREAD_RUNS)?;
    Ok((lat[0].median_ms, lat[1].median_ms))
}

/// Whether the model computes in integers (QDQ or QLinear operators).
fn is_quantized(model: &ModelProto) -> bool {
    model.graph.iter().flat_map(|g| &g.node).any(|n| matches!(n.op_type.as_str(), "QuantizeLinear" | "DequantizeLinear" | "QLinearConv" | "QLinearMatMul"))
}

/// One simulated camera frame for the model's single image input, whose shape must be fixed.
fn fixed_inputs(model: &ModelProto) -> Result<Vec<(String, Tensor)>> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let (name, [_, c, h, w]) = crate::ir::shapes::static_image_input(g, "the tract target")?;
    if c != 1 {
        bail!("the tract target needs a single-channel infrared image input; '{name}' has {c} channels");
    }
    let frame = calibration_frames(None, 1, h, w, 0)?.frames.remove(0).image;
    Ok(vec![(name, frame)])
}

/// tract's NNEF with its ONNX extensions; PyTorch's value names ("onnx::Conv_12") need the
/// extended identifier syntax.
fn nnef() -> tract_nnef::framework::Nnef {
    let mut n = tract_nnef::nnef().with_onnx();
    n.allow_extended_identifier_syntax = true;
    n
}

fn write_nnef(model: &ModelProto, feeds: &[(String, Tensor)], tar: &Path) -> Result<()> {
    // Model metadata (class-name dictionaries and the like) is not needed to run, and its
    // strings do not survive tract's NNEF properties parser.
    let mut bare = model.clone();
    bare.metadata_props.clear();
    let (typed, _, _) = typed_model(&bare, feeds)?;
    let tmp = tar.with_extension("tar.tmp");
    let file = std::fs::File::create(&tmp)?;
    let written = nnef().write_to_tar(&typed, file).map_err(|e| anyhow!("{e:#}"));
    match written {
        Ok(_) => Ok(std::fs::rename(&tmp, tar)?),
        Err(e) => {
            let _ = std::fs::remove_file(&tmp);
            Err(e)
        }
    }
}

/// Outputs of the first run and the median time of `RUNS` runs.
fn timed_runs(rt: &mut dyn Runtime, feeds: &[(String, Tensor)]) -> Result<(crate::runtime::NamedTensors, f64)> {
    let out = rt.run(feeds)?;
    let mut times: Vec<f64> = (0..RUNS)
        .map(|_| {
            let t = Instant::now();
            rt.run(feeds).map(|_| t.elapsed().as_secs_f64() * 1e3)
        })
        .collect::<Result<_>>()?;
    times.sort_by(f64::total_cmp);
    Ok((out, times[RUNS / 2]))
}
