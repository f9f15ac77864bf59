//! Graph rewrites that several layers need. The passes wrap them for recipes; the runtimes,
//! targets and analyses below the passes call them directly.

pub mod bias_pin;
pub mod conv_3d;
pub mod dce;
pub mod space_to_depth;
pub mod split_depthwise;
pub mod tile_columns;
pub mod topo;
pub mod value_info;

/// `narrow-convs-nchw`'s forms (3-D convolutions, pinned biases) back as plain 2-D
/// convolutions, as every later pass and tract take them; returns how many came back.
pub fn lower_narrow_forms(g: &mut crate::onnx::proto::GraphProto) -> anyhow::Result<usize> {
    Ok(conv_3d::lower_all(g)? + bias_pin::unpin_all(g)?)
}

/// Whether `g` holds a form [`lower_narrow_forms`] would lower.
pub fn any_narrow_form(g: &crate::onnx::proto::GraphProto) -> bool {
    conv_3d::any_lifted(g) || bias_pin::any_pinned(g)
}
