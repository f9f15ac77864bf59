//! Splitting nodes into reconstruction-only, detection-only and shared (needed by both).
//!
//! The reconstruction output is recognized as the output shaped like the image input
//! (same channels and H x W): PDI-Net's U-Net returns a frame of the input's size.

use crate::ir::{Graph, Inferred};
use serde::Serialize;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Part {
    ReconstructionOnly,
    DetectionOnly,
    Shared,
    /// Feeds no output at all.
    Dead,
}

pub struct Partition {
    pub image_input: Option<String>,
    pub recon_outputs: Vec<String>,
    pub det_outputs: Vec<String>,
    /// Per node index.
    pub parts: Vec<Part>,
}

/// The image input: the rank-4 input with the largest H x W (the blur map is 6 x 8).
pub fn image_input(g: &Graph, inf: &Inferred) -> Option<String> {
    g.inputs
        .iter()
        .filter_map(|v| inf.types.get(&v.name)?.shape.as_ref().filter(|s| s.len() == 4).map(|s| (v.name.clone(), s[2].max(0) * s[3].max(0))))
        .max_by_key(|(_, area)| *area)
        .map(|(n, _)| n)
}

pub fn partition(g: &Graph, inf: &Inferred) -> Partition {
    let image = image_input(g, inf);
    let image_shape = image.as_ref().and_then(|n| inf.types.get(n)).and_then(|t| t.shape.clone());
    let (mut recon, mut det) = (Vec::new(), Vec::new());
    for o in &g.proto.output {
        let s = inf.types.get(&o.name).and_then(|t| t.shape.clone());
        // Frame-sized, with the input's channels or one (a thermal reconstruction of frames
        // stored as RGB may come out grey).
        let image_like = matches!((&s, &image_shape), (Some(s), Some(i)) if s.len() == 4 && s[2..] == i[2..] && (s[1] == i[1] || s[1] == 1));
        if image_like { recon.push(o.name.clone()) } else { det.push(o.name.clone()) }
    }
    let r = g.cone(recon.iter().map(|s| s.as_str()));
    let d = g.cone(det.iter().map(|s| s.as_str()));
    let parts = r
        .iter()
        .zip(&d)
        .map(|(&r, &d)| match (r, d) {
            (true, true) => Part::Shared,
            (true, false) => Part::ReconstructionOnly,
            (false, true) => Part::DetectionOnly,
            (false, false) => Part::Dead,
        })
        .collect();
    Partition { image_input: image, recon_outputs: recon, det_outputs: det, parts }
}

/// The part an initializer belongs to, from the parts of the nodes reading it.
pub fn combine(a: Option<Part>, b: Part) -> Part {
    match (a, b) {
        (None, b) => b,
        (Some(Part::Dead), b) | (Some(b), Part::Dead) => b,
        (Some(a), b) if a == b => a,
        _ => Part::Shared,
    }
}
