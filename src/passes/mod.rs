//! The passes, one per file. Each states its contract in its doc comment: what it needs,
//! what it guarantees, what it reports.

pub mod pass;

pub use pass::{is_quality_failure, Capability, Pass, PassContext, QualityFailure, Teacher};

use anyhow::{anyhow, bail, Result};

/// The registry: one line per pass, `"recipe-name" => module::Type` (a pass with no options)
/// or `module::Type { options }`. Each line declares the pass's file as a module, lists it in
/// [`KNOWN`], builds it in [`build`] and hands its source to the reference ([`SOURCES`],
/// [`FILES`]).
macro_rules! registry {
    ($($name:literal => $module:ident :: $ty:ident $({ $options:ident })?,)*) => {
        $(pub mod $module;)*

        /// Every pass this build knows, by the name recipes use, in the registry's order.
        pub const KNOWN: &[&str] = &[$($name),*];

        /// Each pass's source text, whose doc comments the generated reference prints.
        pub const SOURCES: &[(&str, &str)] = &[$(($name, include_str!(concat!(stringify!($module), ".rs")))),*];

        /// Each pass's file, relative to the repository.
        pub const FILES: &[(&str, &str)] = &[$(($name, concat!("src/passes/", stringify!($module), ".rs"))),*];

        /// The pass a recipe entry names, with its options as they will run.
        pub fn build(name: &str, options: &yaml_serde::Value) -> Result<Built> {
            match name {
                $($name => registry!(@make name, options, $module::$ty $({ $options })?),)*
                other => bail!("unknown pass '{other}' in the pipeline (known passes: {})", KNOWN.join(", ")),
            }
        }
    };
    (@make $n:ident, $o:ident, $module:ident :: $ty:ident) => { plain($n, $o, Box::new($module::$ty)) };
    (@make $n:ident, $o:ident, $module:ident :: $ty:ident { $options:ident }) => { with($n, $o, |$options| $module::$ty { $options }) };
}

registry! {
    "promote-constants" => promote_constants::PromoteConstants,
    "strip-recon" => strip_recon::StripRecon { options },
    "bind-psf" => bind_psf::BindPsf { options },
    "fold-constants" => fold_constants::FoldConstants { options },
    "fold-psf-gates" => fold_psf_gates::FoldPsfGates { options },
    "fold-bn" => fold_bn::FoldBn { options },
    "resize-to-deconv" => resize_to_deconv::ResizeToDeconv,
    "dce" => dce::Dce,
    "cleanup" => cleanup::Cleanup,
    "drop-classes" => drop_classes::DropClasses,
    "drop-strides" => drop_strides::DropStrides { options },
    "crop-roi" => crop_roi::CropRoi { options },
    "prune" => prune::Prune { options },
    "recover" => recover::Recover { options },
    "quantize" => quantize::Quantize { options },
    "fp16" => to_fp16::ToFp16 { options },
    "rknn-legalize" => rknn_legalize::RknnLegalize { options },
    "rknn-hybrid" => rknn_hybrid::RknnHybrid { options },
    "rknn-qat" => rknn_qat::RknnQat { options },
    "split-wide-depthwise" => split_wide_depthwise::SplitWideDepthwise,
    "tile-conv-columns" => tile_conv_columns::TileConvColumns { options },
    "narrow-convs-nchw" => narrow_convs_nchw::NarrowConvsNchw { options },
    "space-to-depth" => space_to_depth::SpaceToDepth { options },
}

/// A pass built from its recipe entry, with its options as they will run: every default
/// filled in (what the manifest records, so that a rebuild does not depend on defaults).
pub struct Built {
    pub pass: Box<dyn Pass>,
    pub options: yaml_serde::Value,
}

/// A pass that takes no options: any given are an error.
fn plain(name: &str, options: &yaml_serde::Value, pass: Box<dyn Pass>) -> Result<Built> {
    if !options.is_null() && !options.as_mapping().is_some_and(|m| m.is_empty()) {
        bail!("pass {name} takes no options");
    }
    Ok(Built { pass, options: yaml_serde::Value::Null })
}

/// A pass with options from the recipe: missing options take their defaults, unknown ones are
/// errors; the options come back resolved.
fn with<T, P>(name: &str, options: &yaml_serde::Value, make: impl FnOnce(T) -> P) -> Result<Built>
where
    T: serde::de::DeserializeOwned + serde::Serialize + Default,
    P: Pass + 'static,
{
    let options: T = if options.is_null() { T::default() } else { over_defaults(options).map_err(|e| anyhow!("options of pass {name}: {e}"))? };
    let resolved = yaml_serde::to_value(&options).map_err(|e| anyhow!("options of pass {name}: {e}"))?;
    Ok(Built { pass: Box::new(make(options)), options: resolved })
}

/// Options given as a mapping, laid over `T`'s defaults key by key: a key `T` does not have is
/// refused, naming those it has. This is where unknown options are caught, for every pass,
/// since serde cannot deny them beside a flattened field (the shared training schedule); and
/// each pass's defaults fill what a recipe leaves out, the flattened fields' included.
pub(crate) fn over_defaults<T>(given: &yaml_serde::Value) -> std::result::Result<T, String>
where
    T: serde::de::DeserializeOwned + serde::Serialize + Default,
{
    let (Some(given), Ok(yaml_serde::Value::Mapping(mut merged))) = (given.as_mapping(), yaml_serde::to_value(T::default())) else {
        return yaml_serde::from_value(given.clone()).map_err(|e| e.to_string());
    };
    for (k, v) in given {
        if !merged.contains_key(k) {
            let known: Vec<String> = merged.keys().filter_map(|k| k.as_str()).map(|k| format!("`{k}`")).collect();
            return Err(format!("unknown field `{}`, expected one of {}", k.as_str().unwrap_or("?"), known.join(", ")));
        }
        merged.insert(k.clone(), v.clone());
    }
    yaml_serde::from_value(yaml_serde::Value::Mapping(merged)).map_err(|e| e.to_string())
}

/// [`over_defaults`] for an option group that is off by default (`qat: {steps: 400}`).
pub(crate) fn some_over_defaults<'de, D, T>(d: D) -> std::result::Result<Option<T>, D::Error>
where
    D: serde::Deserializer<'de>,
    T: serde::de::DeserializeOwned + serde::Serialize + Default,
{
    use serde::Deserialize;
    let v = yaml_serde::Value::deserialize(d)?;
    if v.is_null() {
        return Ok(None);
    }
    over_defaults(&v).map(Some).map_err(serde::de::Error::custom)
}

/// The graph of a model, or an error naming the pass.
pub(crate) fn graph_mut(model: &mut crate::onnx::proto::ModelProto) -> Result<&mut crate::onnx::proto::GraphProto> {
    model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))
}
