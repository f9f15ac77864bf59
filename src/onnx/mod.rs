//! ONNX: the protobuf schema, file I/O with external data, tensor payloads, small edits.

pub mod attr;
pub mod edit;
pub mod io;
pub mod proto;
pub mod tensor_proto;

pub use io::{load, load_bytes, save, Loaded};
