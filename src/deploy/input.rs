//! What a model takes: its [1, C, H, W] image input, and any other input (the blur map of a
//! model compiled without bind-psf).

use crate::analysis::partition;
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use crate::optics::blur_map::BlurMap;
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};

pub struct ModelInput {
    pub image_input: String,
    pub other_inputs: Vec<String>,
    /// (height, width) of the image input.
    pub shape: (usize, usize),
    /// Channels of the image input: single-channel frames are replicated into them.
    pub channels: usize,
}

impl ModelInput {
    /// `what` names the model in errors ("reference", "the artifact's model").
    pub fn of(model: &ModelProto, what: &str) -> Result<ModelInput> {
        let g = model.graph.as_ref().ok_or_else(|| anyhow!("{what} has no graph"))?;
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        let image_input = partition::image_input(&graph, &inf).ok_or_else(|| anyhow!("{what} has no [1, C, H, W] image input"))?;
        let s = inf.shape(&image_input).ok_or_else(|| anyhow!("{what}'s image input '{image_input}' has no static shape"))?;
        let other_inputs = graph.inputs.iter().map(|v| v.name.clone()).filter(|n| *n != image_input).collect();
        let channels = Some(s[1]).filter(|&c| (1..=16).contains(&c)).ok_or_else(|| anyhow!("{what}'s image input '{image_input}' has {} channels; expected 1 to 16", s[1]))?;
        Ok(ModelInput { shape: (s[2], s[3]), channels, image_input, other_inputs })
    }
}

/// The camera's blur map as the [1, 1, rows, cols] tensor a model with a blur input takes.
pub fn blur_input(path: &std::path::Path) -> Result<Tensor> {
    let m = BlurMap::load(path)?;
    Ok(Tensor::f32(vec![1, 1, m.rows, m.cols], m.values))
}
