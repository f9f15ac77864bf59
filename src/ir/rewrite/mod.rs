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
