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

/// A pass built from its recipe entry, with its options as they will run: every default
/// filled in (what the manifest records, so that a rebuild does not depend on defaults).
pub struct Built {
    pub pass: Box<dyn Pass>,
    pub options: yaml_serde::Value,
}

pub fn build(spec: &PassSpec) -> Result<Built> {
    let plain = |pass: Box<dyn Pass>| -> Result<Built> {
        let empty = spec.options.as_mapping().is_some_and(|m| m.is_empty());
        if !spec.options.is_null() && !empty {
            bail!("pass {} takes no options", spec.name);
        }
        Ok(Built { pass, options: yaml_serde::Value::Null })
    };
    match spec.name.as_str() {
        "promote-constants" => plain(Box::new(promote_constants::PromoteConstants)),
        "strip-recon" => with(spec, |options| strip_recon::StripRecon { options }),
        "bind-psf" => with(spec, |options| bind_psf::BindPsf { options }),
        "fold-constants" => with(spec, |options| fold_constants::FoldConstants { options }),
        "fold-psf-gates" => with(spec, |options| fold_psf_gates::FoldPsfGates { options }),
        "fold-bn" => with(spec, |options| fold_bn::FoldBn { options }),
        "resize-to-deconv" => plain(Box::new(resize_to_deconv::ResizeToDeconv)),
        "dce" => plain(Box::new(dce::Dce)),
        "cleanup" => plain(Box::new(cleanup::Cleanup)),
        "drop-classes" => plain(Box::new(drop_classes::DropClasses)),
        "drop-strides" => with(spec, |options| drop_strides::DropStrides { options }),
        "crop-roi" => with(spec, |options| crop_roi::CropRoi { options }),
        "prune" => with(spec, |options| prune::Prune { options }),
        "recover" => with(spec, |options| recover::Recover { options }),
        "fp16" => with(spec, |options| to_fp16::ToFp16 { options }),
        "quantize" => with(spec, |options| quantize::Quantize { options }),
        "rknn-legalize" => with(spec, |options| rknn_legalize::RknnLegalize { options }),
        "rknn-hybrid" => with(spec, |options| rknn_hybrid::RknnHybrid { options }),
        "rknn-qat" => with(spec, |options| rknn_qat::RknnQat { options }),
        "split-wide-depthwise" => plain(Box::new(split_wide_depthwise::SplitWideDepthwise)),
        "tile-conv-columns" => with(spec, |options| tile_conv_columns::TileConvColumns { options }),
        other => bail!("unknown pass '{other}' in the pipeline (known passes: {})", KNOWN.join(", ")),
    }
}

/// A pass with options from the recipe: missing options take their defaults, unknown ones are
/// errors; the options come back resolved.
fn with<T, P>(spec: &PassSpec, make: impl FnOnce(T) -> P) -> Result<Built>
where
    T: serde::de::DeserializeOwned + serde::Serialize + Default,
    P: Pass + 'static,
{
    let options: T = if spec.options.is_null() { T::default() } else { yaml_serde::from_value(spec.options.clone()).map_err(|e| anyhow!("options of pass {}: {e}", spec.name))? };
    let resolved = yaml_serde::to_value(&options).map_err(|e| anyhow!("options of pass {}: {e}", spec.name))?;
    Ok(Built { pass: Box::new(make(options)), options: resolved })
}

/// The graph of a model, or an error naming the pass.
pub(crate) fn graph_mut(model: &mut crate::onnx::proto::ModelProto) -> Result<&mut crate::onnx::proto::GraphProto> {
    model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))
}
