//! Post-training INT8 quantization: ranges from calibration frames, QDQ emission, error
//! attribution per layer, bias correction, learned rounding and mixed precision. The `quantize` pass drives it.

pub mod at_points;
pub mod attribution;
pub mod collect;
pub mod head_inputs;
pub mod histogram;
pub mod narrow;
pub mod output_bias;
pub mod params;
pub mod plan;
pub mod qat;
pub mod qdq;
pub mod qlinear;
pub mod range;
pub mod rounding;
pub mod speed;
