//! `drop-classes`: the classes a scene does not need leave the head.
//!
//! Needs: `--scene` with `classes`, a recognized YOLOv5 (anchor) or YOLOv8 (DFL) decode with
//! constant Reshape targets and Split sizes (after fold-constants). The model's `names`
//! metadata resolves class names.
//! Does: YOLOv5 keeps each anchor's 5 box/objectness rows and the kept classes' rows of
//! every head convolution; YOLOv8 keeps the kept classes' rows of each level's class
//! convolution. The decode's Split sizes and Reshape targets follow; `names` lists the kept
//! classes in the scene's order and `pdi.scene` maps them to the original indices.
//! Guarantees: boxes, objectness and the kept classes' scores are bit-identical to the
//! original's in f32 (the same rows of the same convolutions, nothing recomputed); so
//! detections after class-aware NMS are the original's decoded on the kept classes' scores.
//! Reports: kept and dropped classes, the convolutions cut, MACs and parameters saved (the
//! runner's before/after counts).

use crate::analysis::channels::detector_convolutions;
use crate::analysis::head::{self, HeadKind};
use crate::ir::{infer, Graph};
use crate::onnx::edit::{initializer, set_input_constant};
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::to_tensor;
use super::{Pass, PassContext};
use crate::scene::{class_names, names_metadata, set_metadata, SceneMeta};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Result};

pub struct DropClasses;

impl Pass for DropClasses {
    fn name(&self) -> &'static str {
        "drop-classes"
    }

    fn provides(&self) -> Vec<super::Capability> {
        vec![super::Capability::Teacher]
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> Result<serde_json::Value> {
        let Some(scene) = cx.scene.as_ref().filter(|s| s.classes.is_some()) else {
            return Ok(serde_json::json!({ "skipped": "the scene names no classes" }));
        };
        let g = super::graph_mut(model)?;
        let (kind, nc, convs, decode, old) = {
            let graph = Graph::build(g)?;
            let inf = infer(&graph);
            let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
            let h = head::detect(&graph, &inf, &outputs);
            let nc = h.classes.ok_or_else(|| anyhow!("drop-classes found no YOLOv5 or YOLOv8 decode with a class count behind the outputs"))?;
            let convs: Vec<(usize, usize)> = detector_convolutions(&graph)
                .into_iter()
                .map(|i| (i, inf.shape(&graph.node(i).output[0]).and_then(|s| s.get(1).copied()).unwrap_or(0)))
                .collect();
            let decode = crate::analysis::channels::decode_nodes(&graph);
            (h.kind, nc, convs, decode, inf)
        };
        let names = class_names(model).unwrap_or_else(|| (0..nc).map(|i| i.to_string()).collect());
        if names.len() != nc {
            bail!("the model's `names` metadata lists {} classes; its head decodes {nc}", names.len());
        }
        let kept = scene.class_indices(&names)?.expect("checked above");
        let before = model.clone();
        let g = super::graph_mut(model)?;
        let mut cut = Vec::new();
        let mut rows_of = Vec::new();
        for (node, channels) in convs {
            let rows: Vec<usize> = match kind {
                HeadKind::Yolov5Anchor if channels % (5 + nc) == 0 => {
                    let no = 5 + nc;
                    (0..channels / no).flat_map(|a| (0..5).chain(kept.iter().map(|c| 5 + c)).map(move |r| a * no + r)).collect()
                }
                HeadKind::Yolov5Anchor => bail!("head convolution '{}' has {channels} channels, not anchors × (5 + {nc})", g.node[node].name),
                HeadKind::Yolov8Dfl if channels == nc => kept.clone(),
                HeadKind::Yolov8Dfl => continue, // the box (DFL) branch
                HeadKind::Raw => bail!("drop-classes needs a YOLOv5 or YOLOv8 decode in the graph; this head is raw"),
            };
            for slot in 1..g.node[node].input.len().min(3) {
                let name = g.node[node].input[slot].clone();
                let t = to_tensor(initializer(g, &name).ok_or_else(|| anyhow!("head convolution '{}' has a non-constant input '{name}'", g.node[node].name))?)?;
                let sliced = t.select(0, &rows).ok_or_else(|| anyhow!("'{name}' does not have {channels} rows"))?;
                set_input_constant(g, node, slot, &sliced, "classes");
            }
            cut.push(serde_json::json!({ "conv": g.node[node].name, "channels": [channels, rows.len()] }));
            rows_of.push((g.node[node].output[0].clone(), rows));
        }
        if cut.is_empty() {
            bail!("drop-classes found no class convolution ({nc} classes) in the head");
        }
        // YOLOv5 splits (xy, wh, objectness + classes), YOLOv8 (boxes, classes).
        let obj = usize::from(kind == HeadKind::Yolov5Anchor);
        let splits = resize_class_splits(g, &decode, nc + obj, kept.len() + obj)?;
        if splits == 0 {
            bail!("drop-classes found no Split separating the {nc} class scores in the decode");
        }
        crate::scene::geometry::follow_shapes(g, &old)?;
        let rows_kept: std::collections::HashMap<String, Vec<usize>> = rows_of.into_iter().collect();
        cx.record_cut(|| before, &rows_kept);

        let kept_names: Vec<String> = kept.iter().map(|&i| names[i].clone()).collect();
        set_metadata(model, "names", &names_metadata(&kept_names));
        let mut meta = SceneMeta::begin(model)?;
        // A model specialized before keeps mapping to the very first model's indices.
        meta.classes = Some(match &meta.classes {
            Some(prev) => kept.iter().map(|&i| prev[i]).collect(),
            None => kept.clone(),
        });
        meta.write(model)?;
        let dropped: Vec<&String> = names.iter().enumerate().filter(|(i, _)| !kept.contains(i)).map(|(_, n)| n).collect();
        Ok(serde_json::json!({ "kept": kept_names, "dropped": dropped, "convolutions": cut, "splits": splits }))
    }
}

/// Split nodes of the decode whose last part (`nc` wide) ends in the class block: it becomes
/// `k` wide. Returns how many.
fn resize_class_splits(g: &mut crate::onnx::proto::GraphProto, decode: &std::collections::HashSet<usize>, nc: usize, k: usize) -> Result<usize> {
    let mut n = 0;
    for i in 0..g.node.len() {
        if !decode.contains(&i) || g.node[i].op_type != "Split" || g.node[i].input.len() < 2 {
            continue;
        }
        let name = g.node[i].input[1].clone();
        let Some(sizes) = initializer(g, &name).and_then(|t| to_tensor(t).ok()).and_then(|t| t.as_i64s()) else { continue };
        if sizes.len() < 2 || *sizes.last().unwrap_or(&0) != nc as i64 {
            continue;
        }
        let mut new = sizes.clone();
        *new.last_mut().expect("two parts") = k as i64;
        set_input_constant(g, i, 1, &Tensor::new(vec![new.len()], TensorData::I64(new)), "classes");
        n += 1;
    }
    Ok(n)
}
