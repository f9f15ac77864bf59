//! `bind-psf`: the camera's blur map becomes a constant of the graph.
//!
//! Needs: a PALS-Bridge whose blur map is a graph input (then `--psf FILE` is required) or a
//! constant (then `--psf` replaces it; without it the baked map stays). Guarantees: the map
//! is an initializer with the file's values; the input is gone from the model's interface.
//! Reports: the map's source before, its name, grid and value range.

use crate::analysis::{bridge, partition};
use crate::ir::{infer, Graph};
use crate::onnx::edit::set_initializer;
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::from_tensor;
use crate::optics::blur_map::BlurMap;
use super::{Pass, PassContext};
use crate::tensor::Tensor;
use anyhow::{bail, Result};

#[derive(serde::Serialize, serde::Deserialize, Default)]
#[serde(deny_unknown_fields)]
pub struct Options {
    /// Blur map file; `--psf` on the command line takes precedence.
    #[serde(default)]
    pub psf: Option<std::path::PathBuf>,
}

pub struct BindPsf {
    pub options: Options,
}

impl Pass for BindPsf {
    fn name(&self) -> &'static str {
        "bind-psf"
    }

    /// A blur map that is a graph input needs `--psf`; a given map must load.
    fn preflight(&self, input: &ModelProto, cx: &PassContext) -> Result<()> {
        if input.graph.is_none() {
            return Ok(());
        }
        match cx.psf.as_ref().or(self.options.psf.as_ref()) {
            None => no_input_map(&blur_maps(input)?),
            Some(file) => BlurMap::load(file).map(|_| ()),
        }
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let maps = blur_maps(model)?;
        let psf_file = cx.psf.as_ref().or(self.options.psf.as_ref());
        if maps.is_empty() {
            if psf_file.is_some() {
                bail!("--psf was given but the model has no PALS-Bridge blur map to bind (not a PDI-Net export, or its map is folded already); compile it without --psf");
            }
            return Ok(serde_json::json!({ "bound": false, "reason": "no PALS-Bridge blur map in the model (not a PDI-Net export, or its map is folded already)" }));
        }
        let Some(file) = psf_file else {
            no_input_map(&maps)?;
            return Ok(serde_json::json!({ "bound": false, "reason": "blur map already constant; no --psf given" }));
        };
        let map = BlurMap::load(file)?;
        let g = super::graph_mut(model)?;
        let mut bound = Vec::new();
        for m in &maps {
            let expected = m.shape.iter().product::<usize>();
            if m.shape[2] != map.rows || m.shape[3] != map.cols || expected != map.values.len() {
                bail!("{}: grid {}x{} does not match the model's blur map {:?}", file.display(), map.rows, map.cols, m.shape);
            }
            let t = from_tensor(&m.name, &Tensor::f32(m.shape.clone(), map.values.clone()));
            if m.source == "input" {
                g.input.retain(|v| v.name != m.name);
            } else if let Some(i) = g.node.iter().position(|n| n.op_type == "Constant" && n.output.first() == Some(&m.name)) {
                g.node.remove(i);
            }
            set_initializer(g, t);
            bound.push(serde_json::json!({ "name": m.name, "was": m.source }));
        }
        let (lo, hi) = map.values.iter().fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        Ok(serde_json::json!({ "bound": true, "maps": bound, "file": file.display().to_string(), "grid": [map.rows, map.cols], "min": lo, "max": hi }))
    }
}

/// The PALS-Bridge blur maps of `model`.
fn blur_maps(model: &ModelProto) -> Result<Vec<bridge::BlurMap>> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow::anyhow!("model has no graph"))?;
    let graph = Graph::build(g)?;
    let inf = infer(&graph);
    let image = partition::image_input(&graph, &inf);
    Ok(bridge::find(&graph, &inf, image.as_deref()).blur_maps)
}

/// Refuses a blur map that is a graph input when no `--psf` was given to bind it.
fn no_input_map(maps: &[bridge::BlurMap]) -> Result<()> {
    match maps.iter().find(|m| m.source == "input") {
        Some(m) => bail!("the blur map '{}' is a graph input: give the camera's calibration with --psf FILE (.npy or .yaml)", m.name),
        None => Ok(()),
    }
}
