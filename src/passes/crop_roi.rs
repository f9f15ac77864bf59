//! `crop-roi`: the model sees only the scene's region of interest.
//!
//! Needs: `--scene` with `roi` (input pixels, x, y, w, h multiples of the model's coarsest
//! stride), one static [1, C, H, W] image input, constant gates and decode constants (after
//! fold-constants and fold-psf-gates).
//! Does: the input becomes the ROI; every position-dependent constant is cropped with it
//! ([`crate::scene::geometry`]): the folded PSF gate maps (the gate at frame pixel (x, y)
//! stays the gate of (x, y): the physics stays where it belongs) and the decode grids and
//! anchor points (boxes come out in full-frame coordinates). `pdi.scene` records the ROI and
//! the frame size; `imgsz` becomes the ROI's.
//! Guarantees: every cropped constant equals the full one's crop bit for bit. The outputs are
//! *not* the full model's: near the crop's edges convolutions see padding, and everywhere the
//! SPPF's pooling and the bridge's squeeze-excitation average over a smaller frame. The
//! pass leaves the full model as the teacher (full frames, cropped values) for `recover`;
//! `verify` measures agreement on reference detections one coarsest stride inside the ROI.
//! Reports: the ROI, the constants cropped, Reshape targets rewritten.

use crate::onnx::proto::ModelProto;
use crate::pipeline::{Pass, PassContext, Teacher};
use crate::scene::geometry::{self, Cut};
use crate::scene::{set_metadata, SceneMeta};
use anyhow::{bail, Result};

pub struct CropRoi;

impl Pass for CropRoi {
    fn name(&self) -> &'static str {
        "crop-roi"
    }

    fn run(&self, model: &mut ModelProto, cx: &PassContext) -> Result<serde_json::Value> {
        let Some(roi) = cx.scene.as_ref().and_then(|s| s.roi) else {
            return Ok(serde_json::json!({ "skipped": "the scene has no roi" }));
        };
        let mut meta = SceneMeta::begin(model)?;
        if meta.roi.is_some() {
            bail!("this model is already cropped to a region of interest; specialize the original model instead");
        }
        let before = model.clone();
        let g = super::graph_mut(model)?;
        let (_, [h, w], levels) = geometry::levels(g)?;
        let report = geometry::apply(g, &Cut { window: roi, keep: vec![true; levels.len()] })?;
        meta.roi = Some(roi);
        // The full model, on full frames, is what recovery distills the cropped one from.
        let mut teacher = cx.teacher.borrow_mut();
        match teacher.as_mut() {
            Some(t) => t.window = Some(roi),
            None => *teacher = Some(Teacher { model: before, kept: Default::default(), window: Some(roi) }),
        }
        drop(teacher);
        meta.write(model)?;
        set_metadata(model, "imgsz", &format!("[{}, {}]", roi.h, roi.w));
        Ok(serde_json::json!({
            "roi": roi,
            "frame": [h, w],
            "pixels_kept": (roi.w * roi.h) as f64 / (w * h) as f64,
            "constants_cropped": report.constants,
            "reshapes_retargeted": report.reshapes,
        }))
    }
}
