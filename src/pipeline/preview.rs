//! `inspect MODEL --scene FILE`: what each key of a scene would remove, before compiling
//! (here, not in `scene`, because it runs pipelines).
//!
//! The model goes through the lossless compile (detect-f32's passes up to `dce`), then each
//! scene pass alone and all of them together, on copies; the preview lists MACs, parameters
//! and outputs of each against the lossless compile. No recovery runs: a crop's accuracy is
//! measured by `verify` after the compile. With an ROI, the preview also measures how much the
//! lossless model's detections inside it depend on what lies outside (`context`), which no
//! crop sees.

use crate::scene::{context, Scene};
use crate::onnx::proto::ModelProto;
use crate::pipeline::{self, counts, PassContext, PassSpec, Recipe};
use anyhow::Result;
use serde::Serialize;
use std::path::PathBuf;

#[derive(Serialize)]
pub struct Row {
    pub what: String,
    pub macs: u64,
    pub params: u64,
    pub macs_ratio: f64,
    pub params_ratio: f64,
    pub outputs: Vec<(String, Vec<usize>)>,
}

#[derive(Serialize)]
pub struct Preview {
    pub rows: Vec<Row>,
    pub context: Option<context::ContextDependence>,
}

pub fn preview(model: &ModelProto, scene: &Scene, psf: Option<PathBuf>, calib: Option<PathBuf>) -> Result<Preview> {
    // The crop's halos are fitted on two frames: their values do not change the counts.
    let options = |n: &str| if n == "crop-roi" { yaml_serde::from_str("{frames: 2}").expect("valid YAML") } else { yaml_serde::Value::Null };
    let recipe = |names: &[&str]| Recipe { name: "scene-preview".into(), description: String::new(), bases: Vec::new(), passes: names.iter().map(|n| PassSpec::new(n, options(n))).collect() };
    let mut base = model.clone();
    pipeline::run(&Recipe::lossless(), &mut base, &mut PassContext { psf: psf.clone(), calib: calib.clone(), ..Default::default() })?;
    let full = counts(&base)?;
    let mut rows = vec![row("lossless compile", &base, full)?];
    let steps: Vec<(&str, Scene)> = [
        ("classes", "drop-classes", Scene { classes: scene.classes.clone(), ..Default::default() }),
        ("object_px", "drop-strides", Scene { object_px: scene.object_px, ..Default::default() }),
        ("roi", "crop-roi", Scene { roi: scene.roi, ..Default::default() }),
    ]
    .into_iter()
    .filter(|(_, _, s)| s.classes.is_some() || s.object_px.is_some() || s.roi.is_some())
    .map(|(_, p, s)| (p, s))
    .collect();
    let mut all = Vec::new();
    for (pass, s) in &steps {
        let mut m = base.clone();
        pipeline::run(&recipe(&[pass]), &mut m, &mut PassContext { scene: Some(s.clone()), calib: calib.clone(), ..Default::default() })?;
        rows.push(row(pass, &m, full)?);
        all.push(*pass);
    }
    if all.len() > 1 {
        let mut m = base.clone();
        pipeline::run(&recipe(&all), &mut m, &mut PassContext { scene: Some(scene.clone()), calib: calib.clone(), ..Default::default() })?;
        rows.push(row("all together", &m, full)?);
    }
    let context = match scene.roi {
        Some(r) => context::measure(&base, r, calib.as_deref(), context::FRAMES, 0, crate::runtime::all_cores())?,
        None => None,
    };
    if scene.roi.is_some() && context.is_none() {
        crate::warn::warn("inspect: the ROI's context dependence is not measured: the model has no decoded YOLOv5 or YOLOv8 detection output");
    }
    Ok(Preview { rows, context })
}

fn row(what: &str, m: &ModelProto, full: pipeline::Counts) -> Result<Row> {
    let c = counts(m)?;
    let g = m.graph.as_ref().ok_or_else(|| anyhow::anyhow!("model has no graph"))?;
    let inf = crate::ir::infer(&crate::ir::Graph::build(g)?);
    Ok(Row {
        what: what.to_string(),
        macs: c.macs,
        params: c.params,
        macs_ratio: c.macs as f64 / full.macs.max(1) as f64,
        params_ratio: c.params as f64 / full.params.max(1) as f64,
        outputs: g.output.iter().map(|o| (o.name.clone(), inf.shape(&o.name).unwrap_or_default())).collect(),
    })
}

impl Preview {
    pub fn render(&self) -> String {
        let mut s = format!("{:<18} {:>14} {:>7} {:>12} {:>7}  outputs\n", "scene", "MACs", "", "params", "");
        for r in &self.rows {
            let outs: Vec<String> = r.outputs.iter().map(|(n, sh)| format!("{n} {sh:?}")).collect();
            s += &format!("{:<18} {:>14} {:>6.3}× {:>12} {:>6.3}×  {}\n", r.what, r.macs, r.macs_ratio, r.params, r.params_ratio, outs.join(", "));
        }
        if let Some(c) = &self.context {
            s += &format!(
                "roi context: the full model's detections inside the ROI (>= {} px from its edges; {} boxes on {} frames) agree mAP@.5:.95 {:.3} (@.5 {:.3}) with those on the same frames with everything outside the ROI taken from another frame; a crop never sees the outside, so the lower this is, the more a crop's detections can differ from the full model's\n",
                c.margin, c.reference_boxes, c.frames, c.agreement, c.agreement50
            );
        }
        s
    }
}
