//! `rknn-hybrid`: which layers RKNN-Toolkit2 should keep in FP16 (its hybrid quantization).
//!
//! Needs: a model from `rknn-legalize` (float, per-stride outputs). Calibration frames come
//! from `--calib`, or the physics pipeline.
//! Guarantees: the graph is unchanged; the chosen layers are stored in the model's metadata
//! (`pdi.rknn_fp16_layers`, a JSON list of {node, input, output}), which `--target rknn`
//! copies into rknn.yaml and `rknn-convert` hands to the toolkit as custom hybrid spans.
//! Reports: the simulated INT8 error before and after, the layers kept and those tried and
//! rejected (the `quantize` pass's mixed-precision search, run on a copy). Layers named in
//! `fp16` are kept whatever the search finds.
//!
//! The simulation mirrors the toolkit's `w8a8 / normal / channel`: symmetric per-channel
//! 8-bit weights, int8 activations with min/max ranges, no bias correction. It is not the
//! toolkit's arithmetic, so the spans are a proposal that `rknn-convert` then measures.

use super::quantize::{Options as QuantizeOptions, Quantize};
use crate::onnx::proto::{ModelProto, StringStringEntryProto};
use super::{Pass, PassContext};
use crate::quant::params::ActivationType;
use crate::targets::rknn_fp16::{Fp16Layer, METADATA_KEY};
use crate::quant::range::Method;
use anyhow::{anyhow, bail, Result};
use serde::Deserialize;


#[derive(serde::Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// Largest rel L2 of any output against float that the INT8 simulation may reach.
    pub error_budget: f64,
    /// At most this many layers in FP16 (each costs NPU time).
    pub max_layers: usize,
    /// Frames that calibrate the simulated INT8 model and measure its error.
    pub calib_frames: usize,
    /// Nodes to keep in FP16 whatever the search finds (the simulation starts with them float).
    pub fp16: Vec<String>,
}

impl Default for Options {
    fn default() -> Self {
        Options { error_budget: 0.05, max_layers: 8, calib_frames: 16, fp16: Vec::new() }
    }
}

pub struct RknnHybrid {
    pub options: Options,
}

impl Pass for RknnHybrid {
    fn name(&self) -> &'static str {
        "rknn-hybrid"
    }

    fn needs(&self) -> Vec<super::Capability> {
        vec![super::Capability::SplitHead]
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        crate::detect::split_head::HeadLayout::from_model(model).map_err(|_| anyhow!("rknn-hybrid needs a model from rknn-legalize: put it after rknn-legalize in the recipe"))?;
        let o = &self.options;
        let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        if let Some(missing) = o.fp16.iter().find(|name| !g.node.iter().any(|n| &n.name == *name)) {
            bail!("rknn-hybrid: fp16 names '{missing}', which is not a node of the legalized model; `pdi-compile inspect` lists the nodes");
        }
        let simulate = Quantize {
            options: QuantizeOptions {
                method: Method::Minmax,
                activations: ActivationType::I8,
                weight_bits: 8,
                calib_frames: o.calib_frames,
                bias_correction: false,
                error_budget: Some(o.error_budget),
                max_float_layers: o.max_layers,
                keep_float: o.fp16.clone(),
                ..QuantizeOptions::default()
            },
        };
        let mut copy = model.clone();
        let report = simulate.run(&mut copy, cx)?;
        let kept = report["mixed_precision"]["kept_float"].as_array().cloned().unwrap_or_default();
        let searched = kept.iter().filter_map(|k| k["node"].as_str());
        let layers: Vec<Fp16Layer> = o
            .fp16
            .iter()
            .map(|s| s.as_str())
            .chain(searched)
            .filter_map(|name| g.node.iter().find(|n| n.name == name))
            .filter_map(|n| Some(Fp16Layer { node: n.name.clone(), input: n.input.first()?.clone(), output: n.output.first()?.clone() }))
            .collect();
        model.metadata_props.retain(|p| p.key != METADATA_KEY);
        model.metadata_props.push(StringStringEntryProto { key: METADATA_KEY.into(), value: serde_json::to_string(&layers)? });
        Ok(serde_json::json!({
            "error_budget": o.error_budget,
            "simulated_int8_worst_rel_l2": report["worst_output_rel_l2"],
            "fp16_layers": layers,
            "tried_and_rejected": report["mixed_precision"]["tried_and_rejected"],
            "calibration": report["calibration"],
        }))
    }
}
