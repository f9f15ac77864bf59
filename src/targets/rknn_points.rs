//! RKNN-Toolkit2's quantization points: the tensors its INT8 plan quantizes, with their
//! types and parameters, as its hybrid-quantization step 1 writes them (`.quantization.cfg`).
//!
//! The toolkit's plan is not an ONNX QDQ plan: it fuses Conv+ReLU (the convolution's output
//! takes the ReLU's range) and Conv+SiLU / Conv+Sigmoid (the activation reads the int32 sum,
//! [`fused_away`]), splits some Concat → Conv pairs per input (`quant::at_points`), quantizes
//! the image and every graph output to int8 and keeps the PSF gates' products in int16. So a
//! model trained for the NPU (`rknn-qat`) trains on these points, and `rknn-convert` writes
//! their ranges back into the toolkit's configuration before it builds.

use super::rknn_toolkit::{pixels, PIXEL_SCALE};
use crate::onnx::proto::{GraphProto, ModelProto, NodeProto, StringStringEntryProto};
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;

/// Metadata key of the points a model was trained on (`rknn-qat`), read by `--target rknn`.
pub const METADATA_KEY: &str = "pdi.rknn_trained_points";

/// One quantized tensor in the toolkit's terms: `dtype` int8 / int16 (asymmetric, per tensor)
/// or float32 (not quantized: the parameters are absent).
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Point {
    /// The graph value the point quantizes, where the toolkit names it otherwise (its
    /// `<input>_int8` and `<output>_int8`); set on trained points.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub value: Option<String>,
    pub dtype: String,
    pub min: Option<f64>,
    pub max: Option<f64>,
    pub scale: Option<f64>,
    pub zero_point: Option<i64>,
}

impl Point {
    /// An int8 point's (scale, zero point), checked: the toolkit's int8 is [-128, 127].
    pub fn int8(&self) -> Option<(f64, i32)> {
        let (s, z) = (self.scale?, self.zero_point?);
        (self.dtype == "int8" && s.is_finite() && s > 0.0 && (-128..=127).contains(&z)).then_some((s, z as i32))
    }

    /// int8 over [lo, hi] as the toolkit derives it (asymmetric, zero exactly representable).
    pub fn int8_covering(lo: f64, hi: f64) -> Point {
        let p = crate::quant::params::QParams::activation(lo, hi, crate::quant::params::ActivationType::I8);
        Point { value: None, dtype: "int8".into(), min: Some(lo), max: Some(hi), scale: Some(p.scale), zero_point: Some(p.zero_point as i64) }
    }
}

/// The toolkit's points for `model` (float, from rknn-legalize; input `input`, outputs
/// `outputs`), calibrated on `frames` ([1, C, H, W] in [0, 1], fed as 8-bit pixels as the
/// NPU gets them) with the target's settings (w8a8, min/max, per-channel weights).
pub fn toolkit_points(model: &ModelProto, frames: &[Tensor], outputs: &[String]) -> Result<BTreeMap<String, Point>> {
    let work = tempfile::tempdir()?;
    crate::onnx::save(model, &work.path().join("model.onnx"))?;
    let mut list = String::new();
    for (i, f) in frames.iter().enumerate() {
        let p = work.path().join(format!("frame_{i:03}.npy"));
        std::fs::write(&p, crate::optics::npy::to_bytes(&f.shape, &pixels(f.as_f32().unwrap_or(&[]))))?;
        list += &format!("{}\n", p.display());
    }
    std::fs::write(work.path().join("dataset.txt"), list)?;
    let channels = frames.first().and_then(|f| f.shape.get(1)).copied().unwrap_or(1);
    let job = serde_json::json!({
        "mode": "points",
        "model": work.path().join("model.onnx"),
        "dataset": work.path().join("dataset.txt"),
        "outputs": outputs,
        "mean_values": [vec![0.0; channels]],
        "std_values": [vec![PIXEL_SCALE; channels]],
        "target_platform": "rk3588",
    });
    let r = super::rknn_toolkit::run(work.path(), &job, None).map_err(|e| anyhow!("rknn-toolkit2 could not plan the quantization: {e:#}"))?;
    serde_json::from_value(r["points"].clone()).map_err(|e| anyhow!("the toolkit's quantization points did not parse: {e}"))
}

/// Why the toolkit's point on `v` is not a quantization in its arithmetic, if it is not: a
/// convolution followed only by a Sigmoid, or by a SiLU (x · sigmoid(x)), runs as one fused
/// op on the int32 sum, so its output is never rounded to int8 (measured: the simulator's
/// dump of such an output equals the float convolution within 1e-6, and quantizing it there
/// misses 21% of the SiLU's outputs by one or two steps). Conv+ReLU fuses too, but rounding
/// the output over the ReLU's range [0, max] is the same arithmetic, so that point stays.
/// A convolution the toolkit splits per concatenated input (`split_outputs`, from
/// `at_points::splits`) ends in an Add, whose output it rounds.
pub fn fused_away(g: &GraphProto, v: &str, split_outputs: &[String]) -> Option<&'static str> {
    let producer = g.node.iter().find(|n| n.output.iter().any(|o| o == v))?;
    if producer.op_type != "Conv" || g.output.iter().any(|o| o.name == v) || split_outputs.iter().any(|o| o == v) {
        return None;
    }
    let readers: Vec<&NodeProto> = g.node.iter().filter(|n| n.input.iter().any(|i| i == v)).collect();
    let sigmoid = readers.iter().find(|n| n.op_type == "Sigmoid")?;
    match readers.len() {
        1 => Some("Conv+Sigmoid: fused, the sigmoid reads the int32 sum"),
        2 if readers.iter().any(|n| n.op_type == "Mul" && n.input.contains(&sigmoid.output[0])) => Some("Conv+SiLU: fused, the SiLU reads the int32 sum"),
        _ => None,
    }
}

/// The points a model was trained on (empty when it was not).
pub fn stored(model: &ModelProto) -> Result<BTreeMap<String, Point>> {
    match model.metadata_props.iter().find(|p| p.key == METADATA_KEY) {
        Some(p) => serde_json::from_str(&p.value).map_err(|e| anyhow!("metadata {METADATA_KEY} is not a map of quantization points: {e}")),
        None => Ok(BTreeMap::new()),
    }
}

/// The int8 parameters of trained points by the graph value each quantizes.
pub fn by_value(points: &BTreeMap<String, Point>) -> BTreeMap<String, (f64, i32)> {
    points.iter().filter_map(|(name, p)| Some((p.value.clone().unwrap_or_else(|| name.clone()), p.int8()?))).collect()
}

pub fn store(model: &mut ModelProto, points: &BTreeMap<String, Point>) -> Result<()> {
    model.metadata_props.retain(|p| p.key != METADATA_KEY);
    model.metadata_props.push(StringStringEntryProto { key: METADATA_KEY.into(), value: serde_json::to_string(points)? });
    Ok(())
}
