//! Scene specialization: what a deployment needs of a detector (classes, object sizes, a
//! region of the frame), read from `--scene FILE`, and what a specialized model remembers of
//! it (`pdi.scene` metadata) so post-processing and `verify` can map it back to the full frame.
//!
//! ```yaml
//! classes: [Car, People]      # names from the model's `names` metadata, or indices
//! object_px: [0, 24]          # smallest and largest object side that matters
//! roi: {x: 0, y: 64, w: 256, h: 128}
//! score_threshold: 0.25
//! max_detections: 100
//! ```

pub mod closed_loop;
pub mod compare;
pub mod context;
pub mod geometry;
pub mod halo;
pub mod levels;
pub mod pool;

use crate::onnx::proto::{ModelProto, StringStringEntryProto};
use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

pub use crate::frames::Roi;

/// A class named by the user: its name in `names`, or its index.
#[derive(Clone, Debug, Deserialize, Serialize, PartialEq)]
#[serde(untagged)]
pub enum ClassRef {
    Index(usize),
    Name(String),
}

/// The scene file.
#[derive(Clone, Debug, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    pub classes: Option<Vec<ClassRef>>,
    pub object_px: Option<[f32; 2]>,
    pub roi: Option<Roi>,
    pub score_threshold: Option<f32>,
    pub max_detections: Option<usize>,
}

impl Scene {
    pub fn load(path: &Path) -> Result<Scene> {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read scene {}", path.display()))?;
        Scene::parse(&text).with_context(|| format!("scene {}", path.display()))
    }

    pub fn parse(text: &str) -> Result<Scene> {
        let s: Scene = match yaml_serde::from_str::<Option<Scene>>(text) {
            Ok(s) => s.unwrap_or_default(),
            Err(e) => bail!("not a scene (keys: classes, object_px, roi, score_threshold, max_detections): {e}"),
        };
        if let Some([lo, hi]) = s.object_px {
            if !(lo.is_finite() && hi.is_finite() && lo >= 0.0 && hi > lo) {
                bail!("object_px [{lo}, {hi}] must be two sizes with 0 <= smallest < largest");
            }
        }
        if let Some(r) = s.roi {
            if r.w == 0 || r.h == 0 {
                bail!("roi {r:?} is empty");
            }
        }
        if let Some(t) = s.score_threshold {
            if !(0.0..1.0).contains(&t) {
                bail!("score_threshold {t} must lie in [0, 1)");
            }
        }
        if s.classes.as_ref().is_some_and(|c| c.is_empty()) {
            bail!("classes is empty: name at least one class, or leave the key out");
        }
        Ok(s)
    }

    /// Class indices in the user's order, resolved against the model's class names.
    pub fn class_indices(&self, names: &[String]) -> Result<Option<Vec<usize>>> {
        let Some(refs) = &self.classes else { return Ok(None) };
        let mut out = Vec::new();
        for r in refs {
            let i = match r {
                ClassRef::Index(i) if *i < names.len() => *i,
                ClassRef::Index(i) => bail!("class index {i} is out of range: the model has {} classes", names.len()),
                ClassRef::Name(n) => names.iter().position(|m| m.eq_ignore_ascii_case(n)).ok_or_else(|| anyhow!("class '{n}' is not one of the model's classes ({})", names.join(", ")))?,
            };
            if out.contains(&i) {
                bail!("class '{}' is listed twice", names[i]);
            }
            out.push(i);
        }
        Ok(Some(out))
    }
}

/// What a specialized model carries in its `pdi.scene` metadata: enough to map its outputs
/// back to the original's (class indices, frame coordinates) and to know what it left out.
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
pub struct SceneMeta {
    /// Original class index of each output class, in output order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub classes: Option<Vec<usize>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub object_px: Option<[f32; 2]>,
    /// Strides the head still decodes (finest first).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strides: Option<Vec<usize>>,
    /// The input is this region of the original frame; boxes come out in frame coordinates.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roi: Option<Roi>,
    /// The original input's (height, width).
    pub frame: [usize; 2],
    /// The original head's strides, finest first: with `frame`, the original's candidates.
    pub full_strides: Vec<usize>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score_threshold: Option<f32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_detections: Option<usize>,
}

pub const METADATA_KEY: &str = "pdi.scene";

impl SceneMeta {
    /// The model's scene metadata; `None` for a model nobody specialized.
    pub fn read(model: &ModelProto) -> Result<Option<SceneMeta>> {
        match metadata(model, METADATA_KEY) {
            None => Ok(None),
            Some(v) => serde_json::from_str(v).map(Some).map_err(|e| anyhow!("metadata '{METADATA_KEY}' is not a scene: {e}")),
        }
    }

    /// The metadata to extend: the model's, or a new one describing the model as it is.
    pub fn begin(model: &ModelProto) -> Result<SceneMeta> {
        if let Some(m) = SceneMeta::read(model)? {
            return Ok(m);
        }
        let g = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let (_, frame, levels) = geometry::levels(g)?;
        Ok(SceneMeta { frame, full_strides: levels.iter().map(|l| l.stride).collect(), ..Default::default() })
    }

    /// The original model's levels.
    pub fn full_levels(&self) -> Vec<geometry::Level> {
        let [h, w] = self.frame;
        self.full_strides.iter().map(|&s| geometry::Level { stride: s, height: h / s, width: w / s }).collect()
    }

    /// The window of the frame the model sees.
    pub fn window(&self) -> Roi {
        let [h, w] = self.frame;
        self.roi.unwrap_or(Roi { x: 0, y: 0, w, h })
    }

    /// For each candidate of the specialized model's decoded output, the original's
    /// candidate it is (`per_cell`: YOLOv5's anchors, 1 for YOLOv8).
    pub fn candidate_map(&self, per_cell: usize) -> Vec<usize> {
        let full = self.full_levels();
        let kept = self.strides.as_ref();
        let keep: Vec<bool> = full.iter().map(|l| kept.is_none_or(|k| k.contains(&l.stride))).collect();
        geometry::candidate_index(&full, &keep, self.window(), per_cell)
    }

    pub fn write(&self, model: &mut ModelProto) -> Result<()> {
        set_metadata(model, METADATA_KEY, &serde_json::to_string(self)?);
        Ok(())
    }

    /// Whether a detection of the original model (class index, box in frame coordinates)
    /// is one this scene keeps: a kept class, a side within `object_px`, inside the ROI at
    /// least `margin` pixels from its edges.
    pub fn keeps(&self, class: usize, b: &[f32; 4], margin: f32) -> bool {
        let class_ok = self.classes.as_ref().is_none_or(|c| c.contains(&class));
        let side = (b[2] - b[0]).max(b[3] - b[1]);
        let size_ok = self.object_px.is_none_or(|[lo, hi]| side >= lo && side <= hi);
        let roi_ok = self.roi.is_none_or(|r| r.contains(b, margin));
        class_ok && size_ok && roi_ok
    }
}

/// Stores the scene's post-processing settings (score threshold, detection cap) in the
/// model's `pdi.scene`, where targets and post-processing read them.
pub fn record_post_processing(model: &mut ModelProto, scene: &Scene) -> Result<()> {
    if scene.score_threshold.is_none() && scene.max_detections.is_none() {
        return Ok(());
    }
    let mut meta = SceneMeta::begin(model)?;
    meta.score_threshold = scene.score_threshold.or(meta.score_threshold);
    meta.max_detections = scene.max_detections.or(meta.max_detections);
    meta.write(model)
}

pub fn metadata<'m>(model: &'m ModelProto, key: &str) -> Option<&'m str> {
    model.metadata_props.iter().find(|p| p.key == key).map(|p| p.value.as_str())
}

pub fn set_metadata(model: &mut ModelProto, key: &str, value: &str) {
    match model.metadata_props.iter_mut().find(|p| p.key == key) {
        Some(p) => p.value = value.to_string(),
        None => model.metadata_props.push(StringStringEntryProto { key: key.into(), value: value.into() }),
    }
}

/// Class names from the exporter's `names` metadata (`{0: 'People', 1: 'Car'}`), in index
/// order; `None` when the model has none.
pub fn class_names(model: &ModelProto) -> Option<Vec<String>> {
    let text = metadata(model, "names")?.trim().trim_start_matches('{').trim_end_matches('}');
    let mut named: Vec<(usize, String)> = Vec::new();
    for item in text.split(',').filter(|s| !s.trim().is_empty()) {
        let (k, v) = item.split_once(':')?;
        named.push((k.trim().parse().ok()?, v.trim().trim_matches(|c| c == '\'' || c == '"').to_string()));
    }
    named.sort();
    named.iter().enumerate().all(|(i, (k, _))| *k == i).then(|| named.into_iter().map(|(_, v)| v).collect())
}

/// The `names` metadata for these names, in the exporter's form.
pub fn names_metadata(names: &[String]) -> String {
    let items: Vec<String> = names.iter().enumerate().map(|(i, n)| format!("{i}: '{n}'")).collect();
    format!("{{{}}}", items.join(", "))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_and_refuses() {
        let s = Scene::parse("classes: [Car, 0]\nobject_px: [0, 24]\nroi: {x: 0, y: 64, w: 256, h: 128}\n").unwrap();
        let names: Vec<String> = ["People", "Car", "Bus"].iter().map(|s| s.to_string()).collect();
        assert_eq!(s.class_indices(&names).unwrap(), Some(vec![1, 0]));
        assert!(Scene::parse("").unwrap().roi.is_none());
        assert!(Scene::parse("clases: [Car]\n").is_err());
        assert!(Scene::parse("object_px: [24, 0]\n").is_err());
        assert!(Scene::parse("roi: {x: 0, y: 0, w: 0, h: 8}\n").is_err());
        assert!(Scene::parse("classes: [Boat]\n").unwrap().class_indices(&names).is_err());
        assert!(Scene::parse("classes: [Car, car]\n").unwrap().class_indices(&names).is_err());
    }

    #[test]
    fn names_round_trip() {
        let mut m = ModelProto::default();
        set_metadata(&mut m, "names", "{0: 'People', 1: 'Car'}");
        let n = class_names(&m).unwrap();
        assert_eq!(n, ["People", "Car"]);
        assert_eq!(names_metadata(&n), "{0: 'People', 1: 'Car'}");
    }
}
