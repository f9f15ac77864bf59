//! What a stressed frame does inside a reduced-precision candidate, layer by layer.
//!
//! INT8: the share of values each QuantizeLinear sees beyond its calibrated range (they
//! clip). FP16: each half-precision value's headroom, max |a| / 65504 (1 overflows to Inf).
//! A probe runs its own session with the values exposed as outputs, so the candidate's own
//! session keeps the kernels ONNX Runtime fuses for it.

use crate::onnx::edit::{expose_outputs, initializer};
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::to_tensor;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::{Tensor, TensorData};
use anyhow::Result;
use serde::Serialize;
use std::collections::HashMap;

/// The largest finite f16.
const F16_MAX: f64 = 65504.0;
/// Layers named per condition in reports.
const WORST_NAMED: usize = 3;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Precision {
    F32,
    Fp16,
    Int8,
}

/// INT8 when the graph quantizes, FP16 when it holds half-precision weights, f32 otherwise.
pub fn precision(m: &ModelProto) -> Precision {
    let Some(g) = m.graph.as_ref() else { return Precision::F32 };
    if g.node.iter().any(|n| matches!(n.op_type.as_str(), "QuantizeLinear" | "QLinearConv" | "DynamicQuantizeLinear")) {
        Precision::Int8
    } else if g.initializer.iter().any(|t| t.data_type == 10) {
        Precision::Fp16
    } else {
        Precision::F32
    }
}

#[derive(Clone, Debug, Serialize)]
pub struct LayerValue {
    pub layer: String,
    pub value: f64,
}

/// One condition's per-layer figure for one candidate.
#[derive(Clone, Debug, Serialize)]
pub struct LayerStats {
    /// "saturation" (share beyond the calibrated range) or "fp16_headroom" (max |a| / 65504).
    pub measure: &'static str,
    pub worst: f64,
    pub mean: f64,
    pub layers: usize,
    /// The worst layers, worst first (what reports name).
    pub worst_layers: Vec<LayerValue>,
    /// Every probed layer, worst first.
    pub per_layer: Vec<LayerValue>,
}

/// A clip range [lo, hi] of one quantized value, and half a step of slack (values within it
/// round into the range).
struct Clip {
    value: String,
    lo: f64,
    hi: f64,
    slack: f64,
}

pub struct Probe {
    rt: OrtRuntime,
    precision: Precision,
    clips: Vec<Clip>,
    /// Per value: (values beyond the range, or max |a|; values seen) since the last `take`.
    acc: HashMap<String, (f64, u64)>,
}

impl Probe {
    /// A probe for an INT8 or FP16 candidate; None for f32 (nothing to saturate).
    pub fn new(m: &ModelProto, threads: usize) -> Result<Option<Probe>> {
        let precision = precision(m);
        let g = m.graph.as_ref().expect("loaded models have a graph");
        let (values, clips) = match precision {
            Precision::F32 => return Ok(None),
            Precision::Int8 => {
                let clips: Vec<Clip> = g.node.iter().filter(|n| n.op_type == "QuantizeLinear" && n.input.len() >= 2).filter_map(|n| clip(g, &n.input)).collect();
                (clips.iter().map(|c| c.value.clone()).collect::<Vec<_>>(), clips)
            }
            Precision::Fp16 => (g.node.iter().flat_map(|n| n.output.iter()).filter(|o| !o.is_empty()).cloned().collect(), Vec::new()),
        };
        // A graph input asked back as an output comes back without a usable buffer from
        // ONNX Runtime 1.31; inputs are read from the feeds instead.
        let inputs: Vec<&str> = g.input.iter().map(|v| v.name.as_str()).collect();
        let values: Vec<String> = values.into_iter().filter(|v| !inputs.contains(&v.as_str())).collect();
        let rt = OrtRuntime::with_options(&expose_outputs(m, &values), ort::session::builder::GraphOptimizationLevel::Level3, threads)?;
        Ok(Some(Probe { rt, precision, clips, acc: HashMap::new() }))
    }

    /// Runs one frame and accumulates every probed value.
    pub fn observe(&mut self, feeds: &[(String, Tensor)]) -> Result<()> {
        let acc = &mut self.acc;
        match self.precision {
            // Quantizer inputs are f32: read them in place, as calibration does.
            Precision::Int8 => self.rt.visit_f32(feeds, |outputs| {
                let by_name: HashMap<&str, &[f32]> = outputs.iter().copied().chain(feeds.iter().filter_map(|(n, t)| Some((n.as_str(), t.as_f32()?)))).collect();
                for c in &self.clips {
                    let Some(v) = by_name.get(c.value.as_str()) else { continue };
                    let beyond = v.iter().filter(|&&x| (x as f64) < c.lo - c.slack || (x as f64) > c.hi + c.slack).count();
                    let slot = acc.entry(c.value.clone()).or_default();
                    *slot = (slot.0 + beyond as f64, slot.1 + v.len() as u64);
                }
            })?,
            Precision::Fp16 => {
                for (name, t) in self.rt.run(feeds)? {
                    if let TensorData::F16(v) = &t.data {
                        let peak = v.iter().map(|x| f64::from(x.to_f32()).abs()).filter(|x| !x.is_nan()).fold(0.0, f64::max);
                        let slot = acc.entry(name).or_default();
                        *slot = (slot.0.max(peak), slot.1 + v.len() as u64);
                    }
                }
            }
            Precision::F32 => {}
        }
        Ok(())
    }

    /// The figures since the last call, and a fresh start.
    pub fn take(&mut self) -> LayerStats {
        let mut per: Vec<LayerValue> = std::mem::take(&mut self.acc)
            .into_iter()
            .map(|(layer, (v, n))| LayerValue { layer, value: if self.precision == Precision::Int8 { v / n.max(1) as f64 } else { v / F16_MAX } })
            .collect();
        per.sort_by(|a, b| b.value.total_cmp(&a.value));
        let mean = per.iter().map(|l| l.value).sum::<f64>() / per.len().max(1) as f64;
        LayerStats {
            measure: if self.precision == Precision::Int8 { "saturation" } else { "fp16_headroom" },
            worst: per.first().map_or(0.0, |l| l.value),
            mean,
            layers: per.len(),
            worst_layers: per.iter().take(WORST_NAMED).cloned().collect(),
            per_layer: per,
        }
    }
}

/// The range a QuantizeLinear(x, scale, zero_point) represents, from its constant scale and
/// zero point (per tensor; a per-channel activation scale takes its widest channel).
fn clip(g: &crate::onnx::proto::GraphProto, inputs: &[String]) -> Option<Clip> {
    if initializer(g, &inputs[0]).is_some() {
        return None; // a weight: its range is its own values
    }
    let scale = to_tensor(initializer(g, &inputs[1])?).ok()?.data.to_f64();
    let zp = inputs.get(2).filter(|z| !z.is_empty()).and_then(|z| to_tensor(initializer(g, z)?).ok());
    let (qmin, qmax, zero) = match zp.as_ref().map(|t| (&t.data, t.data.to_f64())) {
        Some((TensorData::I8(_), z)) => (-128.0, 127.0, z),
        Some((_, z)) => (0.0, 255.0, z), // u8, the ONNX default
        None => (0.0, 255.0, vec![0.0]),
    };
    let (lo, hi, step) = scale.iter().zip(zero.iter().cycle()).fold((f64::MAX, f64::MIN, 0f64), |(lo, hi, st), (&s, &z)| (lo.min((qmin - z) * s), hi.max((qmax - z) * s), st.max(s)));
    (lo <= hi).then(|| Clip { value: inputs[0].clone(), lo, hi, slack: step / 2.0 })
}
