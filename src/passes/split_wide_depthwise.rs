//! `split-wide-depthwise`: a depthwise convolution whose kernel has more taps than tract's
//! vectorized depthwise kernel takes becomes two or four narrower depthwise convolutions over
//! bands of its kernel, summed.
//!
//! Why: tract-core 0.23 runs a depthwise zone through its SIMD kernel only up to
//! [`MAX_TAPS`] taps; past that every output is a scalar loop. The PALS-Bridge's 15x15
//! depthwise convolution (225 taps) took 226 ms of tract's 768 ms on the full-size v5 at
//! 640x480 (ONNX Runtime: 15 ms); split into two 8x15 bands it takes 28 ms.
//!
//! Each band keeps the original's stride and dilation and covers a run of kernel rows (and,
//! for very wide kernels, of columns) that contains the kernel's anchor, so its padding stays
//! non-negative: a band reads the rows it was not given as zero taps. Every product of the
//! original appears in exactly one band, so the result is the original's up to the order of
//! its float sums (the test holds it to ONNX Runtime at rel L2 1e-6). The bias goes to the
//! first band.
//! Needs: f32 weights in an initializer, explicit pads (no `auto_pad`), a 2-D kernel.
//! Reports: the convolutions split (kernel, bands) and the wide ones left, with the reason.

use crate::ir::rewrite::split_depthwise::split_all;
use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use anyhow::Result;

pub use crate::ir::rewrite::split_depthwise::MAX_TAPS;

pub struct SplitWideDepthwise;

impl Pass for SplitWideDepthwise {
    fn name(&self) -> &'static str {
        "split-wide-depthwise"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let g = super::graph_mut(model)?;
        let (split, left) = split_all(g)?;
        Ok(serde_json::json!({ "split": split, "left": left }))
    }
}
