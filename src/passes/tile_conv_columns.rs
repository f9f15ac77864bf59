//! `tile-conv-columns`: a convolution becomes several over column tiles of its input, each
//! at most [`MAX_TILE_WIDTH`] columns wide, their outputs concatenated along the width.
//!
//! Why: tract-core 0.23 runs a float group-1 2-D convolution with at most [`DIRECT_MAX_K`]
//! inputs per output point (channels x taps) over rows of at least 128 points as its direct
//! spatial convolution (a filter along the row, four output channels at a time), and any
//! other as im2col and a matrix product. Neither wins everywhere. The full-size v5 at 640x480
//! on 2 cores (`examples/tract_profile`, one profile each): the 64 -> 128 channel 3x3 of the
//! third encoder stage took 77 ms direct and 19-29 ms as matrix products over tiles, while
//! the 1 -> 32 channel first convolution is fastest direct. A row narrower than 128 points is
//! the one thing a model file can say that steers tract to the matrix product for one
//! convolution, so the tract target times each candidate alone both ways and tiles those
//! that ran faster (`targets::tract_tiles`); this pass is the rewrite, for the nodes named.
//!
//! Each tile is the original convolution over its columns: the same weights and bias, the
//! original's padding on the frame's own edges and none inside, where the neighbouring
//! columns are read instead. So every output is the original's products (in whatever order
//! the runtime sums them: float noise, tested against ONNX Runtime at rel L2 1e-6).
//! Needs: the input's shape known, f32 weights in an initializer, explicit pads, a 2-D
//! kernel, opset 10 or later (Slice with inputs).
//! Reports: the convolutions tiled (width, tiles) and the named ones left, with the reason.

use crate::ir::rewrite::tile_columns::{candidates, tile};
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use anyhow::Result;
use serde::Deserialize;

pub use crate::ir::rewrite::tile_columns::{DIRECT_MAX_K, MAX_TILE_WIDTH};

#[derive(serde::Serialize, Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Options {
    /// The convolutions to tile, by node name.
    #[serde(default)]
    pub nodes: Vec<String>,
}

pub struct TileConvColumns {
    pub options: Options,
}

impl Pass for TileConvColumns {
    fn name(&self) -> &'static str {
        "tile-conv-columns"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let plans = candidates(model)?;
        let g = super::graph_mut(model)?;
        let (mut tiled, mut left) = (Vec::new(), Vec::new());
        for name in &self.options.nodes {
            match plans.iter().find(|(n, _)| n == name) {
                Some((_, Ok(plan))) => {
                    tile(g, plan)?;
                    tiled.push(serde_json::json!({ "node": name, "width": plan.width, "tiles": plan.tiles.len() }));
                }
                Some((_, Err(why))) => left.push(serde_json::json!({ "node": name, "reason": why })),
                None => left.push(serde_json::json!({ "node": name, "reason": "not a float group-1 2-D convolution tract would run directly, or not the only node of that name" })),
            }
        }
        Ok(serde_json::json!({ "tiled": tiled, "left": left }))
    }
}
