//! The passes, one per file. Each states its contract in its doc comment: what it needs,
//! what it guarantees, what it reports.

pub mod bind_psf;
pub mod cleanup;
pub mod crop_roi;
pub mod dce;
pub mod drop_classes;
pub mod drop_strides;
pub mod fold_bn;
pub mod fold_constants;
pub mod fold_psf_gates;
pub mod promote_constants;
pub mod prune;
pub mod quantize;
pub mod recover;
pub mod resize_to_deconv;
pub mod rknn_hybrid;
pub mod rknn_legalize;
pub mod rknn_qat;
pub mod split_wide_depthwise;
pub mod strip_recon;
pub mod tile_conv_columns;
pub mod to_fp16;

use crate::pipeline::{Pass, PassSpec};
use anyhow::{anyhow, bail, Result};

/// Every pass this build knows, by the name recipes use.
pub const KNOWN: &[&str] = &["promote-constants", "strip-recon", "bind-psf", "fold-constants", "fold-psf-gates", "fold-bn", "resize-to-deconv", "dce", "cleanup", "drop-classes", "drop-strides", "crop-roi", "prune", "recover", "quantize", "fp16", "rknn-legalize", "rknn-hybrid", "rknn-qat", "split-wide-depthwise", "tile-conv-columns"];

pub fn build(spec: &PassSpec) -> Result<Box<dyn Pass>> {
    Ok(match spec.name.as_str() {
        "promote-constants" => Box::new(promote_constants::PromoteConstants),
        "strip-recon" => Box::new(strip_recon::StripRecon { options: options(spec)? }),
        "bind-psf" => Box::new(bind_psf::BindPsf { options: options(spec)? }),
        "fold-constants" => Box::new(fold_constants::FoldConstants { options: options(spec)? }),
        "fold-psf-gates" => Box::new(fold_psf_gates::FoldPsfGates { options: options(spec)? }),
        "fold-bn" => Box::new(fold_bn::FoldBn { options: options(spec)? }),
        "resize-to-deconv" => Box::new(resize_to_deconv::ResizeToDeconv),
        "dce" => Box::new(dce::Dce),
        "cleanup" => Box::new(cleanup::Cleanup),
        "drop-classes" => Box::new(drop_classes::DropClasses),
        "drop-strides" => Box::new(drop_strides::DropStrides { options: options(spec)? }),
        "crop-roi" => Box::new(crop_roi::CropRoi { options: options(spec)? }),
        "prune" => Box::new(prune::Prune { options: options(spec)? }),
        "recover" => Box::new(recover::Recover { options: options(spec)? }),
        "fp16" => Box::new(to_fp16::ToFp16 { options: options(spec)? }),
        "quantize" => Box::new(quantize::Quantize { options: options(spec)? }),
        "rknn-legalize" => Box::new(rknn_legalize::RknnLegalize { options: options(spec)? }),
        "rknn-hybrid" => Box::new(rknn_hybrid::RknnHybrid { options: options(spec)? }),
        "rknn-qat" => Box::new(rknn_qat::RknnQat { options: options(spec)? }),
        "split-wide-depthwise" => Box::new(split_wide_depthwise::SplitWideDepthwise),
        "tile-conv-columns" => Box::new(tile_conv_columns::TileConvColumns { options: options(spec)? }),
        other => bail!("unknown pass '{other}' in the pipeline (known passes: {})", KNOWN.join(", ")),
    })
}

/// A pass's options from the recipe; missing options take their defaults, unknown ones are errors.
fn options<T: serde::de::DeserializeOwned + Default>(spec: &PassSpec) -> Result<T> {
    if spec.options.is_null() {
        return Ok(T::default());
    }
    yaml_serde::from_value(spec.options.clone()).map_err(|e| anyhow!("options of pass {}: {e}", spec.name))
}

/// The graph of a model, or an error naming the pass.
pub(crate) fn graph_mut(model: &mut crate::onnx::proto::ModelProto) -> Result<&mut crate::onnx::proto::GraphProto> {
    model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))
}
