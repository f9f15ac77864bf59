//! Comparing a scene-specialized model with the full original on what the scene keeps.
//!
//! The candidate sees the ROI crop of each frame; the reference the whole frame. The
//! reference's decoded output is gathered into the candidate's layout (its candidates on the
//! kept levels inside the ROI, its kept classes' columns), so per-group errors compare like
//! with like. Detections are compared where the scene needs them: the reference's, on the
//! kept classes, with the larger side within `object_px`, inside the ROI at least one
//! coarsest stride from its edges (a convolution near the crop's edge sees padding where the
//! full model saw pixels); the candidate's are held to the same region and sizes.

use super::SceneMeta;
use crate::analysis::head::HeadKind;
use crate::detect::Detection;
use crate::frames::Frame;
use crate::metrics::coco_map::Truth;
use crate::onnx::proto::ModelProto;
use crate::tensor::Tensor;
use anyhow::{anyhow, bail, Result};

pub struct SceneView {
    pub meta: SceneMeta,
    kind: HeadKind,
    /// Reference candidate of each candidate row/column.
    candidates: Vec<usize>,
    /// Reference channels of each candidate channel of the decoded output.
    channels: Vec<usize>,
    /// Distance from the ROI's edges a detection must keep to be compared.
    pub margin: f32,
}

impl SceneView {
    /// The view for a candidate that carries `pdi.scene`; `None` for an ordinary candidate.
    pub fn new(candidate: &ModelProto, kind: HeadKind, reference_classes: usize, reference_frame: (usize, usize)) -> Result<Option<SceneView>> {
        let Some(meta) = SceneMeta::read(candidate)? else { return Ok(None) };
        if (meta.frame[0], meta.frame[1]) != reference_frame {
            bail!("the candidate was specialized from a {}x{} model; the reference takes {}x{} frames", meta.frame[1], meta.frame[0], reference_frame.1, reference_frame.0);
        }
        // Leading box (and objectness) channels, and candidates per cell: YOLOv5 has one per anchor.
        let (lead, per_cell) = match kind {
            HeadKind::Yolov5Anchor => (5, anchors_per_cell(candidate).ok_or_else(|| anyhow!("cannot tell the candidate's anchors per cell from its detection output"))?),
            HeadKind::Yolov8Dfl => (4, 1),
            HeadKind::Raw => bail!("a scene-specialized candidate is compared through its decoded output; the reference's head is raw"),
        };
        let classes: Vec<usize> = meta.classes.clone().unwrap_or_else(|| (0..reference_classes).collect());
        let channels = (0..lead).chain(classes.iter().map(|c| lead + c)).collect();
        let margin = if meta.roi.is_some() { meta.full_strides.iter().copied().max().unwrap_or(0) as f32 } else { 0.0 };
        Ok(Some(SceneView { candidates: meta.candidate_map(per_cell), channels, kind, meta, margin }))
    }

    /// The view of `student` against `teacher` (the model before the scene passes), when the
    /// student is scene-specialized and the teacher is not.
    pub fn of_teacher(student: &ModelProto, teacher: &ModelProto) -> Result<Option<SceneView>> {
        if SceneMeta::read(teacher)?.is_some() || SceneMeta::read(student)?.is_none() {
            return Ok(None);
        }
        let g = teacher.graph.as_ref().ok_or_else(|| anyhow!("teacher has no graph"))?;
        let graph = crate::ir::Graph::build(g)?;
        let inf = crate::ir::infer(&graph);
        let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
        let head = crate::analysis::head::detect(&graph, &inf, &outputs);
        let (_, [h, w], _) = super::geometry::levels(g)?;
        SceneView::new(student, head.kind, head.classes.unwrap_or(0), (h, w))
    }

    /// A feed of full frames, cropped to what the candidate sees.
    pub fn crop_feed(&self, feed: &[(String, Tensor)]) -> Result<Vec<(String, Tensor)>> {
        feed.iter().map(|(n, t)| Ok((n.clone(), if t.shape.len() == 4 { self.crop_image(t)? } else { t.clone() }))).collect()
    }

    /// The ROI of a [1, C, H, W] frame (the frame itself when the scene has no ROI).
    fn crop_image(&self, t: &Tensor) -> Result<Tensor> {
        let Some(r) = self.meta.roi else { return Ok(t.clone()) };
        r.crop(t).ok_or_else(|| anyhow!("frame of shape {:?} does not hold the ROI", t.shape))
    }

    /// One line on what is compared.
    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        if let Some(c) = &self.meta.classes {
            parts.push(format!("classes {c:?} of the original"));
        }
        if let Some([lo, hi]) = self.meta.object_px {
            parts.push(format!("objects {lo}..{hi} px"));
        }
        if let Some(r) = self.meta.roi {
            parts.push(format!("inside the ROI {}x{} at ({}, {}) by {} px", r.w, r.h, r.x, r.y, self.margin));
        }
        format!("scene-specialized candidate: compared on {}", parts.join(", "))
    }

    /// The frame the candidate sees.
    pub fn crop(&self, f: &Frame) -> Result<Frame> {
        Ok(Frame { image: self.crop_image(&f.image)?, ..f.clone() })
    }

    /// The reference's decoded output in the candidate's layout.
    pub fn gather(&self, t: &Tensor) -> Result<Tensor> {
        let (cand_axis, chan_axis) = match self.kind {
            HeadKind::Yolov5Anchor => (1, 2),
            _ => (2, 1),
        };
        t.select(cand_axis, &self.candidates)
            .and_then(|t| t.select(chan_axis, &self.channels))
            .ok_or_else(|| anyhow!("the reference's detection output {:?} does not match the candidate's scene", t.shape))
    }

    /// The reference's decoded output with only the kept classes' columns, every candidate
    /// kept: decoding it picks each candidate's best *kept* class, as the candidate does, while
    /// objects on dropped levels or outside the ROI still count against the candidate.
    pub fn kept_classes(&self, t: &Tensor) -> Result<Tensor> {
        let axis = if self.kind == HeadKind::Yolov5Anchor { 2 } else { 1 };
        t.select(axis, &self.channels).ok_or_else(|| anyhow!("the reference's detection output {:?} does not have the scene's classes", t.shape))
    }

    /// Reference detections (decoded from [`Self::kept_classes`], so in the candidate's class
    /// indices) that the scene keeps.
    pub fn reference_detections(&self, ds: Vec<Detection>) -> Vec<Detection> {
        ds.into_iter().filter(|d| self.meta.keeps(self.to_original_class(d.class), &d.bbox, self.margin)).collect()
    }

    /// Candidate detections in the scene's sizes and region (classes are the scene's already).
    pub fn candidate_detections(&self, ds: Vec<Detection>) -> Vec<Detection> {
        ds.into_iter().filter(|d| self.meta.keeps(self.to_original_class(d.class), &d.bbox, self.margin)).collect()
    }

    /// Labels the scene keeps, with the candidate's class indices.
    pub fn labels(&self, ts: &[Truth]) -> Vec<Truth> {
        ts.iter().filter(|t| self.meta.keeps(t.class, &t.bbox, self.margin)).map(|t| Truth { class: self.to_candidate_class(t.class), bbox: t.bbox }).collect()
    }

    fn to_candidate_class(&self, c: usize) -> usize {
        self.meta.classes.as_ref().and_then(|k| k.iter().position(|&x| x == c)).unwrap_or(c)
    }

    fn to_original_class(&self, c: usize) -> usize {
        self.meta.classes.as_ref().and_then(|k| k.get(c).copied()).unwrap_or(c)
    }
}

/// YOLOv5 anchors per cell: the candidate's decoded rows over its cells.
fn anchors_per_cell(candidate: &ModelProto) -> Option<usize> {
    let g = candidate.graph.as_ref()?;
    let (_, _, levels) = super::geometry::levels(g).ok()?;
    let cells: usize = levels.iter().map(|l| l.height * l.width).sum();
    let graph = crate::ir::Graph::build(g).ok()?;
    let inf = crate::ir::infer(&graph);
    let rows = g.output.iter().filter_map(|o| inf.shape(&o.name)).find(|s| s.len() == 3)?[1];
    (cells > 0 && rows % cells == 0).then(|| rows / cells)
}
