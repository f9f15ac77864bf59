//! The tract target's choice of convolution form: each convolution tract-core 0.23 would run
//! as its direct spatial convolution is timed alone on tract, whole and in column tiles
//! (`tile-conv-columns`, which steers tract to im2col and a matrix product), and ships tiled
//! where that ran faster.
//!
//! Why measured, one convolution at a time: which form wins depends on the channels, the
//! row length and the CPU. The full-size v5 at 640x480 on 2 x86 cores, each convolution
//! alone (input and output copies included): the encoder's 64 -> 128 channel 3x3 took 110 ms
//! whole against 36 ms tiled, its 1 -> 32 channel first one 61 against 131. Like the INT8
//! choice, this follows the machine that compiles; tract.yaml lists every candidate with both
//! timings, so a deployment on another CPU can see what was chosen and why.

use crate::onnx::edit::{initializer, tensor_value_info};
use crate::onnx::proto::{GraphProto, ModelProto, TensorTypeProto, TypeProto, TypeValue, ValueInfoProto};
use crate::ir::rewrite::tile_columns::{candidates, tile, Plan};
use crate::runtime::tract_runtime::TractRuntime;
use crate::tensor::{DType, Tensor};
use crate::runtime::latency::interleaved;
use anyhow::{anyhow, Result};

/// Timed runs of each form (interleaved; the median decides).
const RUNS: usize = 7;
/// The tiles must be this much faster, on the median and on the fastest run, to be shipped:
/// one convolution timed against itself this way differs by a few percent here.
const MIN_GAIN: f64 = 0.05;

#[derive(serde::Serialize)]
pub struct ConvForm {
    pub node: String,
    pub tiles: usize,
    pub whole_ms: f64,
    pub tiled_ms: f64,
    pub tiled: bool,
}

/// Tiles the convolutions of `model` that ran faster tiled on `threads` threads; returns
/// every candidate with its timings, and warns (leaving it whole) where one could not be timed.
pub fn choose(model: &mut ModelProto, threads: usize) -> Result<Vec<ConvForm>> {
    let mut forms = Vec::new();
    for (name, plan) in candidates(model)? {
        let Ok(plan) = plan else { continue };
        match time_both(model, &plan, threads) {
            Ok((whole_ms, tiled_ms, fastest)) => {
                let tiled = tiled_ms < whole_ms * (1.0 - MIN_GAIN) && fastest.1 < fastest.0 * (1.0 - MIN_GAIN);
                if tiled {
                    tile(model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?, &plan)?;
                }
                forms.push(ConvForm { node: name, tiles: plan.tiles.len(), whole_ms, tiled_ms, tiled });
            }
            Err(e) => crate::warn::warn(format!("tract target: convolution '{name}' left whole, it could not be timed alone: {e:#}")),
        }
    }
    Ok(forms)
}

/// Tiles the convolutions named in `tiled` (an earlier build's timed choice) without timing;
/// a name that is not a candidate here is an error: the model is not the one that was timed.
pub fn apply(model: &mut ModelProto, tiled: &[String]) -> Result<Vec<ConvForm>> {
    let plans: Vec<(String, Plan)> = candidates(model)?.into_iter().filter_map(|(n, p)| p.ok().map(|p| (n, p))).collect();
    let mut forms = Vec::new();
    for name in tiled {
        let (_, plan) = plans.iter().find(|(n, _)| n == name).ok_or_else(|| anyhow!("the recorded build tiled convolution '{name}', which this model does not have; it is not the model that build timed"))?;
        tile(model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?, plan)?;
        forms.push(ConvForm { node: name.clone(), tiles: plan.tiles.len(), whole_ms: f64::NAN, tiled_ms: f64::NAN, tiled: true });
    }
    Ok(forms)
}

/// Median times of the convolution alone, whole and tiled, and their fastest runs.
fn time_both(model: &ModelProto, plan: &Plan, threads: usize) -> Result<(f64, f64, (f64, f64))> {
    let whole = alone(model, plan)?;
    let mut tiled = whole.clone();
    tile(tiled.graph.as_mut().expect("built with a graph"), plan)?;
    let n: usize = plan.input.iter().product();
    // Speed does not depend on the values; a fixed ramp keeps runs comparable.
    let x = Tensor::f32(plan.input.clone(), (0..n).map(|i| (i % 251) as f32 / 251.0).collect());
    let feeds = vec![("x".to_string(), x)];
    let mut a = TractRuntime::new(&whole, &feeds, threads)?;
    let mut b = TractRuntime::new(&tiled, &feeds, threads)?;
    let lat = interleaved(&mut [("whole".into(), &mut a, feeds.clone()), ("tiled".into(), &mut b, feeds.clone())], RUNS)?;
    Ok((lat[0].median_ms, lat[1].median_ms, (lat[0].min_ms, lat[1].min_ms)))
}

/// A model of the one convolution of `plan`: input "x" of its shape, its weights, output "y".
fn alone(model: &ModelProto, plan: &Plan) -> Result<ModelProto> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let mut node = g.node.iter().find(|n| n.name == plan.node).ok_or_else(|| anyhow!("no node named '{}'", plan.node))?.clone();
    let weights = node.input[1..]
        .iter()
        .filter(|s| !s.is_empty())
        .map(|s| initializer(g, s).cloned().ok_or_else(|| anyhow!("its input '{s}' is not a constant")))
        .collect::<Result<Vec<_>>>()?;
    node.input[0] = "x".into();
    node.output = vec!["y".into()];
    // The output's shape is left to the runtime.
    let y = ValueInfoProto { name: "y".into(), r#type: Some(TypeProto { value: Some(TypeValue::TensorType(TensorTypeProto { elem_type: DType::F32.onnx_code(), shape: None })), denotation: String::new() }), ..Default::default() };
    let graph = GraphProto { name: "conv".into(), node: vec![node], initializer: weights, input: vec![tensor_value_info("x", DType::F32, &plan.input)], output: vec![y], ..Default::default() };
    Ok(ModelProto { ir_version: model.ir_version, opset_import: model.opset_import.clone(), graph: Some(graph), ..Default::default() })
}
