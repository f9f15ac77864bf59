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
//! Where the ROI's edge is not the frame's, every padded convolution and pooling reads a halo
//! instead of zeros: rows estimated from the crop's own edge, fitted on calibration frames to
//! the full model's values (`halo: linear`, the default; `mean`; `zero`: no halo; see
//! [`crate::scene::halo`]), and every global average pooling maps the ROI's channel means to
//! an estimate of the frame's ([`crate::scene::pool`]). Frames come from `--calib` or the
//! physics pipeline.
//! Guarantees: every cropped constant equals the full one's crop bit for bit. The outputs are
//! *not* the full model's: the halos and the pooled means are estimates. The pass leaves the
//! full model as the teacher (full frames, cropped values) for `recover`, with the halos' and
//! pools' constants as what `recover: {train: estimates}` trains; `verify` measures agreement
//! on reference detections one coarsest stride inside the ROI.
//! Reports: the ROI, the constants cropped, Reshape targets rewritten, the halos (values,
//! padded reads, and per side their error on the calibration frames relative to zero padding's),
//! and per pool the chosen fit and its held-out error relative to the uncorrected mean's.

use crate::onnx::proto::ModelProto;
use super::{Pass, PassContext};
use crate::calib_frames::image_feeds;
use crate::ir::{infer, Graph};
use crate::scene::geometry::{self, Cut};
use crate::scene::closed_loop;
use crate::scene::halo::Mode;
use crate::scene::{set_metadata, SceneMeta};
use anyhow::{bail, Result};

/// Past a few rows the fit has many times the weights of the rows it estimates.
const MAX_HALO_ROWS: usize = 4;

#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Options {
    /// What stands in for the pixels outside the ROI at each padded convolution: `linear` (a 1x1
    /// convolution of the edge rows plus an intercept, fitted to the full model), `mean` (the
    /// fitted mean alone) or `zero` (plain zero padding).
    pub halo: Mode,
    /// Rows (columns) in from the ROI's edge each halo reads: 1, the edge alone, is cheapest
    /// (a 1x1 convolution) and agreed best. Measured on the trained models' ROI crop (200
    /// held-out frames, open-loop fits; agreement mAP@0.5:0.95, then the classes' rel L2
    /// inside the ROI, v5 w0.25 / v8 w0.25 / tiny): 1 row 0.986 / 0.980 / 0.906 and 0.114 / 0.056 / 0.155; 2 rows
    /// 0.979 / 0.979 / 0.893 and 0.109 / 0.048 / 0.141; 3 rows 0.980 / 0.979 / 0.901 and 0.106 /
    /// 0.048 / 0.137. More rows fit the outputs closer, yet do not agree better: agreement turns
    /// on the few detections near the score threshold. Choosing per strip by held-out fit error
    /// (tried) did worse than any fixed count on the v5.
    pub halo_rows: usize,
    /// Calibration frames the halos are fitted on. The deepest map's edge has 8 positions a
    /// frame at 256x192, so 64 frames give its up to 256-channel fit 512 samples (with a
    /// ridge); fitted so, the v5 w0.25's crop agreed 0.986 on 200 held-out frames.
    pub frames: usize,
    /// Whether global average pools get the frame-mean correction (with any halo but `zero`).
    pub pools: bool,
    /// Whether each halo and pool correction is fitted on the crop's own values, with the
    /// estimates upstream of it in place ([`crate::scene::closed_loop`]), rather than on the
    /// full model's. Off by default: it runs the crop once per wave (38 waves on the trained
    /// w0.25 models: crop-roi took 16-23 s instead of 2-3), and alone it agreed no better.
    pub closed_loop: bool,
    /// Seed of the simulated calibration frames (when no `--calib`).
    pub seed: u64,
}

impl Default for Options {
    fn default() -> Self {
        Options { halo: Mode::Linear, halo_rows: 1, frames: 64, pools: true, closed_loop: false, seed: 0 }
    }
}

pub struct CropRoi {
    pub options: Options,
}

impl Pass for CropRoi {
    fn name(&self) -> &'static str {
        "crop-roi"
    }

    fn provides(&self) -> Vec<super::Capability> {
        vec![super::Capability::Teacher]
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
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
        let constants = float_initializers(model);
        let halos = self.halos(model, &before, roi, [h, w], cx)?;
        let estimates: Vec<String> = float_initializers(model).difference(&constants).cloned().collect();
        meta.roi = Some(roi);
        // The full model, on full frames, is what recovery distills the cropped one from.
        cx.record_window(|| before, roi, estimates);
        meta.write(model)?;
        set_metadata(model, "imgsz", &format!("[{}, {}]", roi.h, roi.w));
        Ok(serde_json::json!({
            "roi": roi,
            "frame": [h, w],
            "pixels_kept": (roi.w * roi.h) as f64 / (w * h) as f64,
            "constants_cropped": report.constants,
            "reshapes_retargeted": report.reshapes,
            "halo": halos,
        }))
    }
}

/// The names of a model's float initializers.
fn float_initializers(model: &ModelProto) -> std::collections::BTreeSet<String> {
    // ONNX's FLOAT is data type 1.
    model.graph.iter().flat_map(|g| &g.initializer).filter(|t| t.data_type == 1).map(|t| t.name.clone()).collect()
}

impl CropRoi {
    fn halos(&self, model: &mut ModelProto, full: &ModelProto, roi: crate::frames::Roi, frame: [usize; 2], cx: &PassContext) -> Result<serde_json::Value> {
        let o = &self.options;
        if o.halo == Mode::Zero {
            return Ok(serde_json::json!({ "mode": o.halo }));
        }
        if !(1..=MAX_HALO_ROWS).contains(&o.halo_rows) {
            bail!("crop-roi's halo_rows is {}; use 1 to {MAX_HALO_ROWS}", o.halo_rows);
        }
        if o.frames == 0 {
            bail!("crop-roi's halos need frames > 0 (or `halo: zero`)");
        }
        let graph = Graph::build(full.graph.as_ref().expect("checked by graph_mut"))?;
        let (feeds, source) = image_feeds(&graph, &infer(&graph), cx.calib.as_deref(), o.frames, o.seed.wrapping_add(29))?;
        let fitted = closed_loop::fit(model, full, roi, frame, &feeds, o.halo, o.halo_rows, o.pools, o.closed_loop, crate::runtime::all_cores())?;
        let r = fitted.halos;
        Ok(serde_json::json!({
            "mode": o.halo,
            "values": r.values,
            "reads": r.reads,
            "frames": r.frames,
            "calibration": source,
            "closed_loop_waves": fitted.waves,
            "rel_error_vs_zero": r.rel_error,
            "pools": fitted.pools,
        }))
    }
}
