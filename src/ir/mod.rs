//! The intermediate representation: an index over an ONNX graph, shape inference and costs.
//!
//! The `ModelProto` stays the source of truth (that is what keeps round trips lossless);
//! [`Graph`] adds what passes and analyses need: producers, consumers, topological order.

pub mod cost;
pub mod graph;
pub mod rewrite;
pub mod shapes;

pub use graph::Graph;
pub use shapes::{infer, Inferred, ValueType};
