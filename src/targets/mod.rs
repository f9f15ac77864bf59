//! Deployment targets: what `compile --target` writes beside the model so that the folder
//! is what ships.

pub mod rknn;
pub mod rknn_convert;
pub mod rknn_fp16;
pub mod rknn_points;
pub mod rknn_toolkit;
pub mod tract;
pub mod tract_tiles;

/// Where the compiled model goes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Target {
    /// DIR/model.onnx for any ONNX runtime.
    #[default]
    Onnx,
    /// DIR/model.onnx checked on tract with fixed shapes, an NNEF archive where it loads
    /// faster, and DIR/tract.yaml with the measurements.
    Tract,
    /// DIR/model.onnx from rknn-legalize with DIR/rknn.yaml, DIR/dataset.txt and the
    /// calibration frames it lists: the input of `pdi-compile rknn-convert DIR`.
    Rknn,
}
