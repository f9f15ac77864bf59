//! What the coverage-guided fuzzers in `fuzz/` (cargo-afl, stable Rust) run, and what the
//! test suite replays their saved corpus and crash inputs through: each target takes raw
//! bytes and must return, whatever the bytes. An `Err` is the right answer to bad input; a
//! panic, an abort, a hang or an unbounded allocation is a bug.

use crate::ir::{infer, Graph};

/// The targets by name, as `fuzz/` and the replay test call them.
pub const TARGETS: [(&str, fn(&[u8])); 7] = [
    ("onnx", onnx),
    ("recipe", recipe),
    ("scene", scene),
    ("gate", gate),
    ("conditions", conditions),
    ("npy", npy),
    ("image", image),
];

/// The ONNX loader and the checks every command runs next: graph building, shape
/// inference, the inspect report (head, bridge, partition, costs).
pub fn onnx(data: &[u8]) {
    let Ok(loaded) = crate::onnx::load_bytes(data, None) else { return };
    let Some(g) = loaded.model.graph.as_ref() else { return };
    if let Ok(graph) = Graph::build(g) {
        let _ = infer(&graph);
    }
    let _ = crate::inspect::inspect(&loaded.model);
}

/// Pipeline recipes (YAML), down to every pass's options.
pub fn recipe(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(r) = crate::pipeline::recipe::Recipe::parse(text) {
        for spec in &r.passes {
            let _ = crate::pipeline::build_pass(spec);
        }
    }
}

/// Scene files.
pub fn scene(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = crate::scene::Scene::parse(text);
    }
}

/// verify's and stress's gate files.
pub fn gate(data: &[u8]) {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = yaml_serde::from_str::<crate::verify::gate::Gate>(text);
        let _ = yaml_serde::from_str::<crate::stress::gate::StressGate>(text);
    }
}

/// Stress condition files, expanded and applied to a small frame.
pub fn conditions(data: &[u8]) {
    let Ok(text) = std::str::from_utf8(data) else { return };
    if let Ok(set) = crate::optics::conditions::parse(text, std::path::Path::new("/nonexistent")) {
        let frame = crate::tensor::Tensor::f32(vec![1, 1, 8, 8], (0..64).map(|i| i as f32 / 64.0).collect());
        for c in set.conditions.iter().take(8) {
            let _ = c.apply_tensor(&frame, 1);
        }
    }
}

/// `.npy` arrays (blur maps, frames).
pub fn npy(data: &[u8]) {
    let _ = crate::optics::npy::parse(data);
}

/// Frame images (PNG, TIFF) as the frame loader decodes them.
pub fn image(data: &[u8]) {
    let _ = crate::frames::decode_bytes(data);
}
