//! Recognizing PDI-Net's parts in an ONNX graph: which outputs are which, the PALS-Bridge,
//! and the detector head.

pub mod bridge;
pub mod channels;
pub mod head;
pub mod partition;
