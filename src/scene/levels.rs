//! Which detection levels (strides) a model's detections come from, measured on calibration
//! frames, and the cut that removes levels: what `drop-strides` does for a scene's object
//! sizes and `prune` (`unused_levels`) for levels a model never uses.

use super::geometry::{self, Cut, CutReport, Level};
use super::{Roi, SceneMeta};
use crate::analysis::head::{Head, HeadKind};
use crate::calib_frames::image_feeds;
use crate::detect::{decode, nms::nms, Detection};
use crate::ir::{infer, Graph};
use crate::onnx::proto::ModelProto;
use crate::runtime::{ort_runtime::OrtRuntime, Runtime};
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};
use std::path::Path;

/// Where the measurement's frames come from and which detections it counts.
pub struct Measure<'a> {
    /// Calibration frames (`--calib`), or simulated ones from `seed`.
    pub calib: Option<&'a Path>,
    pub frames: usize,
    pub seed: u64,
    /// Only detections whose larger side lies in this range (input pixels) count.
    pub size: [f32; 2],
    /// Score threshold of a detection.
    pub score: f32,
}

/// Each level's share of the model's final detections (one NMS over all levels, as
/// deployment runs it) that `m` counts, and where the frames came from with how many
/// detections they held.
pub fn detection_shares(model: &ModelProto, head: &Head, levels: &[Level], m: &Measure) -> Result<(Vec<f64>, String)> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let (feeds, source) = {
        let graph = Graph::build(g)?;
        image_feeds(&graph, &infer(&graph), m.calib, m.frames, m.seed)?
    };
    let output = head.output.clone().ok_or_else(|| anyhow!("the detection output has no static 3-D shape"))?;
    let mut rt = OrtRuntime::new(model)?;
    let iou = if head.kind == HeadKind::Yolov8Dfl { 0.7 } else { 0.6 };
    let [lo, hi] = m.size;
    let mut counts = vec![0usize; levels.len()];
    for f in &feeds {
        let outs = rt.run(f)?;
        let t = &outs.iter().find(|(n, _)| *n == output).ok_or_else(|| anyhow!("output '{output}' missing"))?.1;
        // Candidates tagged by level through their rank in the output, then one NMS over all.
        let per_level = split_levels(head.kind, t, levels)?;
        let mut all: Vec<(Detection, usize)> = Vec::new();
        for (li, part) in per_level.iter().enumerate() {
            all.extend(decode::candidates(head.kind, part, m.score)?.into_iter().map(|d| (d, li)));
        }
        let kept = nms(all.iter().map(|p| p.0).collect(), iou, 300);
        for d in kept {
            let side = (d.bbox[2] - d.bbox[0]).max(d.bbox[3] - d.bbox[1]);
            if side >= lo && side <= hi {
                if let Some((_, li)) = all.iter().find(|(c, _)| *c == d) {
                    counts[*li] += 1;
                }
            }
        }
    }
    let total = counts.iter().sum::<usize>().max(1) as f64;
    Ok((counts.iter().map(|&c| c as f64 / total).collect(), format!("{source}; {} detections counted", counts.iter().sum::<usize>())))
}

/// Removes the levels whose `keep` is false (their head convolutions and the nodes only they
/// feed go with dead code elimination) and records the strides left in the model's scene
/// metadata, so `run` and `verify` map its candidates back to the full head's. `object_px`
/// is the scene's size range, when a scene asked for it.
pub fn drop_levels(model: &mut ModelProto, keep: &[bool], object_px: Option<[f32; 2]>) -> Result<CutReport> {
    if !keep.iter().any(|&k| k) {
        bail!("internal: a cut that keeps no detection level");
    }
    let mut meta = SceneMeta::begin(model)?;
    let g = model.graph.as_mut().ok_or_else(|| anyhow!("model has no graph"))?;
    let (_, [h, w], levels) = geometry::levels(g)?;
    let cut = geometry::apply(g, &Cut { window: Roi { x: 0, y: 0, w, h }, keep: keep.to_vec() })?;
    meta.object_px = object_px.or(meta.object_px);
    meta.strides = Some(levels.iter().zip(keep).filter(|(_, &k)| k).map(|(l, _)| l.stride).collect());
    meta.write(model)?;
    super::set_metadata(model, "stride", &format!("{:?}", meta.strides.as_ref().expect("set")));
    Ok(cut)
}

/// The decoded output cut into its levels' candidates.
fn split_levels(kind: HeadKind, t: &Tensor, levels: &[Level]) -> Result<Vec<Tensor>> {
    let cells: usize = levels.iter().map(|l| l.height * l.width).sum();
    let axis = if kind == HeadKind::Yolov5Anchor { 1 } else { 2 };
    let n = *t.shape.get(axis).ok_or_else(|| anyhow!("detection output has shape {:?}", t.shape))?;
    if n % cells != 0 {
        bail!("detection output has {n} candidates; the levels have {cells} cells");
    }
    let k = n / cells;
    let mut at = 0;
    levels
        .iter()
        .map(|l| {
            let m = k * l.height * l.width;
            let idx: Vec<usize> = (at..at + m).collect();
            at += m;
            t.select(axis, &idx).ok_or_else(|| anyhow!("cannot split the detection output"))
        })
        .collect()
}
