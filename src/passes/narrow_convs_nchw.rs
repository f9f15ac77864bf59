//! `narrow-convs-nchw`: each group-1 convolution with fewer than `below` input and output
//! channels becomes a 3-D convolution over a unit axis (Unsqueeze, Conv, Squeeze), which
//! ONNX Runtime runs in NCHW; with `form: bias`, it stays 2-D and reads its bias through a
//! DequantizeLinear (`ir::rewrite::bias_pin`), which keeps it on ONNX Runtime's 2-D NCHW
//! kernels: the 2-D im2col, not the 3-D form's generic one. The 3-D form stays the default:
//! it does not lean on which nodes ONNX Runtime folds, and record `latency-640` times the
//! two forms against each other on the pruned models (docs/results/latency.md).
//!
//! Why: on x86, ONNX Runtime's NCHWc layout transform takes every float 2-D convolution with
//! fewer input channels than its block (16 with AVX-512, 8 with AVX2) to its blocked kernel,
//! which computes and writes the output padded to whole blocks; the next narrow
//! convolution reads NCHW, so a reorder follows each one. A pruned encoder layer with 2
//! output channels at 640x480 computes 16 and moves 8 times its bytes twice. The transform
//! takes 4-D weights only, so a 3-D convolution stays on the NCHW kernels. Against the same
//! model in 2-D, in one loop at 640x480 on 2 AVX-512 cores (four `latency-640` records):
//! the pruned width-0.25 v5 in INT8 0.83x, 0.80x, 0.72x and 0.89x, in float 0.96x, 0.76x,
//! 0.78x and 0.83x; the unpruned one 0.97x, 0.84x, 0.91x and 0.86x. The full-width pruned
//! v5, with two such layers, gains nothing (record `latency-640-full`: 1.01x in float, 1.07x
//! in INT8).
//!
//! The same products summed the same way (float noise, held to ONNX Runtime at rel L2
//! 1e-6 by the test; in an INT8 model the noise flips a QuantizeLinear's rounding here and
//! there, rel L2 about 1e-3). An activation that alone reads a convolution moves inside the
//! pair, where ONNX Runtime fuses it. Every later pass gets 2-D convolutions back (the runner
//! lowers them first, under their own names), and so do tract and its target: a recipe
//! ends with this pass, and one built on such a recipe ends with it again.
//! Needs: f32 weights in an initializer, a 2-D kernel; `form: bias` an opset of 13 or later
//! (a per-channel DequantizeLinear; before it, the 3-D form). Reports: each convolution
//! rewritten (channels in and out, its form, the activation moved with it).

use crate::ir::rewrite::bias_pin::pin;
use crate::ir::rewrite::conv_3d::{lift, narrow};
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use anyhow::{bail, Result};
use serde::Deserialize;

#[derive(serde::Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Options {
    /// A convolution is rewritten when both its input and its output channels are fewer
    /// than this: ONNX Runtime's NCHWc block on AVX-512 (on AVX2 it is 8).
    pub below: usize,
    /// How each is kept off the blocked kernels: `3d` (a 3-D convolution over a unit axis)
    /// or `bias` (2-D, its bias read through a DequantizeLinear).
    #[serde(default)]
    pub form: Form,
}

#[derive(serde::Serialize, Deserialize, Clone, Copy, PartialEq, Eq, Default, Debug)]
pub enum Form {
    #[default]
    #[serde(rename = "3d")]
    ThreeD,
    #[serde(rename = "bias")]
    Bias,
}

impl Default for Options {
    fn default() -> Self {
        Options { below: 16, form: Form::ThreeD }
    }
}

pub struct NarrowConvsNchw {
    pub options: Options,
}

impl Pass for NarrowConvsNchw {
    fn name(&self) -> &'static str {
        "narrow-convs-nchw"
    }

    fn check(&self) -> Result<()> {
        if !(2..=4096).contains(&self.options.below) {
            bail!("below must be 2 to 4096 channels");
        }
        Ok(())
    }

    fn takes_lifted_convs(&self) -> bool {
        true
    }

    fn takes_space_to_depth(&self) -> bool {
        true
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let opset = crate::onnx::edit::default_opset(model).unwrap_or(13);
        let g = super::graph_mut(model)?;
        let mut rewritten = Vec::new();
        let bias = self.options.form == Form::Bias && opset >= 13;
        // Last first: a rewrite inserts nodes, which moves the indices after it.
        for (i, cin, cout) in narrow(g, self.options.below).into_iter().rev() {
            let node = g.node[i].name.clone();
            let (form, activation) = if bias {
                pin(g, i)?;
                ("bias", None)
            } else {
                ("3d", lift(g, i, opset)?)
            };
            rewritten.push(serde_json::json!({ "node": node, "channels": [cin, cout], "form": form, "activation": activation }));
        }
        rewritten.reverse();
        Ok(serde_json::json!({ "rewritten": rewritten }))
    }
}
