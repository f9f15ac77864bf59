//! Training on random crops of large frames: a step on a 256x192 window of a 640x480 frame
//! costs what a 256x192 step costs. The network is convolutional, so the only things tied to
//! the frame are constants shaped like it (the folded PSF gate maps, one value per pixel of a
//! feature grid): each step cuts them to the window with the frame, for the student and the
//! teacher alike. Anything else that fixes a shape from the frame's size (a Reshape, a Resize
//! to fixed sizes) cannot follow a crop and is refused before training.
//!
//! Crops are asked for by size, not by default: a crop is not the frame the model will see.
//! On a 256x192 window the stride-32 grid is 8x6 cells, and a model whose scores read that
//! far (the 640x480 YOLOv8: its teacher's class scores inside a crop differ from its own on
//! the whole frame by a rel L2 of 0.63, the YOLOv5's by 0.1) teaches its student scores it
//! never gives on the camera's frames. `auto` trains on whole frames and reads the batch as
//! frames of 256x192, so a step holds about the pixels the recipe's batch was chosen with.

use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use anyhow::{anyhow, bail, Result};
use std::collections::BTreeMap;

/// The frame (width, height) `auto` reads a batch in.
const AUTO: (usize, usize) = (256, 192);

/// The `crop` option of the training passes: `auto` (whole frames, the batch counted in
/// frames of 256x192), `none` (whole frames, the batch as written), or `WxH` (random crops).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Crop {
    #[default]
    Auto,
    Off,
    /// Width, height.
    Size(usize, usize),
}

impl std::str::FromStr for Crop {
    type Err = anyhow::Error;
    fn from_str(s: &str) -> Result<Crop> {
        match s {
            "auto" => Ok(Crop::Auto),
            "none" => Ok(Crop::Off),
            _ => {
                let (w, h) = s.split_once('x').ok_or_else(|| anyhow!("crop must be auto, none or WxH (e.g. 256x192), not '{s}'"))?;
                let side = |v: &str| v.parse::<usize>().ok().filter(|&v| v > 0 && v % 32 == 0);
                match (side(w), side(h)) {
                    (Some(w), Some(h)) => Ok(Crop::Size(w, h)),
                    _ => bail!("crop '{s}': both sides must be positive multiples of 32"),
                }
            }
        }
    }
}

impl std::fmt::Display for Crop {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        match self {
            Crop::Auto => write!(f, "auto"),
            Crop::Off => write!(f, "none"),
            Crop::Size(w, h) => write!(f, "{w}x{h}"),
        }
    }
}

impl serde::Serialize for Crop {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl<'de> serde::Deserialize<'de> for Crop {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Crop, D::Error> {
        String::deserialize(d)?.parse().map_err(serde::de::Error::custom)
    }
}

impl Crop {
    /// The crop (height, width) for frames of `frame` (height, width), or None to train on
    /// whole frames.
    pub fn resolve(&self, frame: (usize, usize)) -> Result<Option<(usize, usize)>> {
        let (fh, fw) = frame;
        match *self {
            Crop::Off | Crop::Auto => Ok(None),
            Crop::Size(w, h) if w > fw || h > fh => bail!("crop {w}x{h} is larger than the {fw}x{fh} frames"),
            Crop::Size(w, h) if (w, h) == (fw, fh) => Ok(None),
            Crop::Size(w, h) => Ok(Some((h, w))),
        }
    }
}

/// Frames per step for a schedule's `batch` on frames of `frame` (height, width), split
/// among `devices`. With `auto`, frames larger than 256x192 take fewer a step, about the
/// pixels of `batch` frames of 256x192 (rounded up, and up to a multiple of `devices`): the
/// 640x480 v8 trained elsewhere kept 0.981x of its mAP after 8000 steps of 2 whole frames
/// against 0.892x after 8000 of 8 crops, in the same time. Otherwise `batch`.
pub fn frames_per_step(crop: Crop, batch: usize, frame: (usize, usize), devices: usize) -> usize {
    let (pixels, auto) = (frame.0 * frame.1, AUTO.0 * AUTO.1);
    if crop != Crop::Auto || pixels <= auto {
        return batch;
    }
    let devices = devices.max(1);
    (batch * auto).div_ceil(pixels).div_ceil(devices) * devices
}

/// What the worker needs to train on crops: the crop's size, the grid its offsets fall on,
/// and each model's frame-shaped constants with their stride.
#[derive(serde::Serialize, Debug, PartialEq)]
pub struct Plan {
    pub h: usize,
    pub w: usize,
    /// Offsets and sides are multiples of it: every feature grid (and every constant's
    /// stride) divides it, so a crop's cells are cells of the whole frame.
    pub step: usize,
    pub student: BTreeMap<String, usize>,
    pub teacher: BTreeMap<String, usize>,
}

/// The crop plan for training `student` towards `teacher` on the values each is matched by
/// (the head and feature values), frames of `frame` (height, width), or None when `crop`
/// resolves to whole frames. Refuses, in one line, a model a crop cannot follow.
pub fn plan(crop: Crop, student: (&ModelProto, &[String]), teacher: (&ModelProto, &[String]), frame: (usize, usize)) -> Result<Option<Plan>> {
    let Some((h, w)) = crop.resolve(frame)? else { return Ok(None) };
    let (s_consts, s_step) = frame_shaped(student.0, student.1, frame)?;
    let (t_consts, t_step) = frame_shaped(teacher.0, teacher.1, frame)?;
    let mut step = lcm(32, lcm(s_step, t_step));
    for s in s_consts.values().chain(t_consts.values()) {
        step = lcm(step, *s);
    }
    if h % step != 0 || w % step != 0 {
        bail!("crop {w}x{h}: both sides must be multiples of {step}, the model's coarsest grid");
    }
    Ok(Some(Plan { h, w, step, student: s_consts, teacher: t_consts }))
}

/// The constants of `model` that the cone of `values` reads and that are shaped like the
/// frame on some feature grid (the last two dimensions the frame's divided by a stride), with
/// that stride; and the coarsest grid of `values` themselves.
fn frame_shaped(model: &ModelProto, values: &[String], frame: (usize, usize)) -> Result<(BTreeMap<String, usize>, usize)> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let (fh, fw) = frame;
    let cone = graph.cone(values.iter().map(String::as_str));
    let mut step = 1;
    for v in values {
        if let Some(s) = inf.shape(v).filter(|s| s.len() == 4 && s[2] > 0 && s[3] > 0) {
            step = lcm(step, (fh / s[2]).max(fw / s[3]).max(1));
        }
    }
    // Conv weights and the kernels their DequantizeLinear reads are shaped by the kernel.
    let mut kernels = std::collections::HashSet::new();
    let in_cone = || g.node.iter().enumerate().filter(|(i, _)| cone[*i]).map(|(_, n)| n);
    for n in in_cone() {
        if matches!(n.op_type.as_str(), "Conv" | "ConvTranspose") {
            if let Some(w) = n.input.get(1) {
                kernels.insert(w.as_str());
                if let Some(dq) = graph.producer_of(w).filter(|d| d.op_type == "DequantizeLinear") {
                    kernels.insert(dq.input[0].as_str());
                }
            }
        }
    }
    let mut consts = BTreeMap::new();
    for n in in_cone() {
        refuse_fixed_shape(n, &graph)?;
        for input in n.input.iter().filter(|v| !v.is_empty() && !kernels.contains(v.as_str())) {
            let Some(dims) = constant_dims(&graph, input) else { continue };
            if dims.len() < 3 || (dims[dims.len() - 2] <= 1 && dims[dims.len() - 1] <= 1) {
                continue;
            }
            let (a, b) = (dims[dims.len() - 2] as usize, dims[dims.len() - 1] as usize);
            let stride = (1..=64).find(|s| fh % s == 0 && fw % s == 0 && fh / s == a && fw / s == b);
            match stride {
                Some(s) if dims.len() == 4 => {
                    consts.insert(input.clone(), s);
                }
                _ => bail!("cannot train on crops: constant '{input}' {dims:?} (read by {}) is shaped like an image but not like the {fw}x{fh} frame on a feature grid; set crop: none", crate::ir::graph::describe(n)),
            }
        }
    }
    Ok((consts, step))
}

/// The dimensions of `value` when it is an initializer or a Constant node's output.
fn constant_dims(graph: &Graph, value: &str) -> Option<Vec<i64>> {
    if let Some(t) = graph.initializers.get(value) {
        return Some(t.dims.clone());
    }
    let n = graph.producer_of(value).filter(|n| n.op_type == "Constant")?;
    n.attribute.iter().find(|a| a.name == "value").and_then(|a| a.t.as_ref()).map(|t| t.dims.clone())
}

/// Refuses a node whose output shape a constant fixes from the frame's size: it cannot run
/// on a crop.
fn refuse_fixed_shape(n: &crate::onnx::proto::NodeProto, graph: &Graph) -> Result<()> {
    let constant = |k: usize| n.input.get(k).is_some_and(|v| !v.is_empty() && constant_dims(graph, v).is_some());
    let fixed = match n.op_type.as_str() {
        "Reshape" | "Expand" | "Tile" | "ConstantOfShape" => true,
        // Resize by `sizes` (its fourth input); by scales it follows the input.
        "Resize" => constant(3),
        _ => false,
    };
    if fixed {
        bail!("cannot train on crops: {} fixes its output's shape from the frame's size; set crop: none", crate::ir::graph::describe(n));
    }
    Ok(())
}

fn lcm(a: usize, b: usize) -> usize {
    fn gcd(a: usize, b: usize) -> usize {
        if b == 0 { a } else { gcd(b, a % b) }
    }
    a / gcd(a, b) * b
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn crop_option_reads_and_resolves() {
        assert_eq!("auto".parse::<Crop>().unwrap(), Crop::Auto);
        assert_eq!("none".parse::<Crop>().unwrap(), Crop::Off);
        assert_eq!("256x192".parse::<Crop>().unwrap(), Crop::Size(256, 192));
        assert!("250x192".parse::<Crop>().is_err());
        assert!("256".parse::<Crop>().is_err());
        assert_eq!(Crop::Auto.resolve((480, 640)).unwrap(), None, "auto trains on whole frames");
        assert_eq!(Crop::Auto.resolve((192, 256)).unwrap(), None);
        assert_eq!(Crop::Size(256, 192).resolve((480, 640)).unwrap(), Some((192, 256)));
        assert_eq!(Crop::Size(320, 256).resolve((480, 640)).unwrap(), Some((256, 320)));
        assert_eq!(Crop::Size(640, 480).resolve((480, 640)).unwrap(), None);
        assert!(Crop::Size(704, 480).resolve((480, 640)).is_err());
        assert_eq!(Crop::Off.resolve((480, 640)).unwrap(), None);
    }

    #[test]
    fn auto_counts_the_batch_in_frames_of_256x192() {
        // 8 x 256x192 is 1.28 frames of 640x480: 2 a step, 4 among 4 devices.
        assert_eq!(frames_per_step(Crop::Auto, 8, (480, 640), 1), 2);
        assert_eq!(frames_per_step(Crop::Auto, 8, (480, 640), 4), 4);
        assert_eq!(frames_per_step(Crop::Auto, 2, (480, 640), 1), 1);
        assert_eq!(frames_per_step(Crop::Auto, 32, (480, 640), 1), 6);
        // At or below 256x192, and for every other setting, the batch as written.
        assert_eq!(frames_per_step(Crop::Auto, 8, (192, 256), 1), 8);
        assert_eq!(frames_per_step(Crop::Auto, 8, (96, 128), 1), 8);
        assert_eq!(frames_per_step(Crop::Off, 8, (480, 640), 1), 8);
        assert_eq!(frames_per_step(Crop::Size(256, 192), 8, (480, 640), 1), 8);
    }
}
