//! `space-to-depth`: each narrow block at full resolution (stride-1 convolutions of at most
//! `max_channels` channels and their activations, ended by a 2x2 max pooling) runs on 2x2
//! pixel blocks: SpaceToDepth, the convolutions on four times the channels at half the height
//! and width, the pooling as the maximum of the four pixel positions (Split, Max).
//!
//! Why: the semi-U-Net encoder's first block (1 -> 8 -> 8 channels at the camera's 640x480)
//! moves a full-resolution map per layer at a few GMAC/s. ONNX Runtime's float kernels pad
//! 8 channels to their 16-channel blocks and reorder each map back; its integer
//! convolution is slower still below 16 output channels, so INT8 left the block float. On
//! blocks the layers are 4 -> 32 -> 32 channels at 320x240, which both kernels run at full
//! width: four times the multiplications (3x3), a fraction of the time. What it bought, in
//! one interleaved loop each: `latency-640` and `latency-256` in docs/results/latency.md.
//! tract, whose convolutions follow their multiplications, gets the block back as it was
//! (the tract runtime and its target lower it; on the block alone tract ran the rewritten
//! form 2.1x slower), and so does every pass after this one that does not take it (only
//! `narrow-convs-nchw` and `quantize` do, the latter unless it trains through torch, whose
//! interpreter has no SpaceToDepth): pruning and training see the model's own layers.
//!
//! The same products summed in another order (float noise, held to ONNX Runtime at rel L2
//! 1e-6 by the test). Needs: a block's input with a static, even height and width; f32
//! weights in initializers; kernels of odd size padded to keep the size. Reports: each block
//! rewritten (its convolutions with their channels in and out, the input's shape).

use crate::ir::rewrite::space_to_depth::{blocks, rewrite};
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use anyhow::{bail, Result};
use serde::Deserialize;

#[derive(serde::Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Options {
    /// A block is rewritten when every convolution in it has at most this many input and
    /// output channels (on blocks: four times as many).
    pub max_channels: usize,
}

impl Default for Options {
    fn default() -> Self {
        Options { max_channels: 8 }
    }
}

pub struct SpaceToDepth {
    pub options: Options,
}

impl Pass for SpaceToDepth {
    fn name(&self) -> &'static str {
        "space-to-depth"
    }

    fn check(&self) -> Result<()> {
        if !(1..=1024).contains(&self.options.max_channels) {
            bail!("max_channels must be 1 to 1024");
        }
        Ok(())
    }

    fn takes_space_to_depth(&self) -> bool {
        true
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let opset = crate::onnx::edit::default_opset(model).unwrap_or(13);
        let g = super::graph_mut(model)?;
        let mut rewritten = Vec::new();
        // The last block first: a rewrite inserts nodes, which moves the indices after it.
        let mut found = blocks(g, self.options.max_channels)?;
        found.sort_by_key(|b| std::cmp::Reverse(b.pool));
        for block in &found {
            let convs: Vec<serde_json::Value> = block
                .nodes
                .iter()
                .filter(|&&i| g.node[i].op_type == "Conv")
                .zip(&block.channels)
                .map(|(&i, &(cin, cout))| serde_json::json!({ "node": g.node[i].name, "channels": [cin, cout] }))
                .collect();
            rewritten.push(serde_json::json!({ "pool": g.node[block.pool].name, "convolutions": convs, "input": block.input }));
            rewrite(g, block, opset)?;
        }
        rewritten.reverse();
        Ok(serde_json::json!({ "rewritten": rewritten }))
    }
}
