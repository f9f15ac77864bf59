//! The layers RKNN-Toolkit2 keeps in FP16 (its hybrid quantization): chosen by the
//! `rknn-hybrid` pass, stored in the model's metadata, copied into rknn.yaml by `--target rknn`.

use crate::onnx::proto::ModelProto;
use anyhow::{anyhow, Result};
use serde::{Deserialize, Serialize};

/// The metadata key: a JSON list of [`Fp16Layer`].
pub const METADATA_KEY: &str = "pdi.rknn_fp16_layers";

/// One layer for the toolkit: the span from `input` to `output` runs in FP16.
#[derive(Serialize, Deserialize, Clone, Debug, PartialEq)]
pub struct Fp16Layer {
    pub node: String,
    pub input: String,
    pub output: String,
}

/// The layers stored by `rknn-hybrid` (none when it did not run).
pub fn stored(model: &ModelProto) -> Result<Vec<Fp16Layer>> {
    match model.metadata_props.iter().find(|p| p.key == METADATA_KEY) {
        Some(p) => serde_json::from_str(&p.value).map_err(|e| anyhow!("metadata {METADATA_KEY} is not a list of layers: {e}")),
        None => Ok(Vec::new()),
    }
}
