//! The YAML form of a pipeline.
//!
//! ```yaml
//! name: detect-f32
//! description: what it is for
//! passes:
//!   - strip-recon                 # a pass with default options
//!   - prune: {ratio: 0.5}         # a pass with options
//! ```
//!
//! A recipe can start from another: `base: detect-lossless` runs that recipe's passes first
//! (less those named in `without: [..]`), then its own. The base is a sibling file of that
//! name, else the shipped recipe; a loaded recipe holds the expanded list, which is what the
//! manifest records and a rebuild runs.

use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PassSpec {
    pub name: String,
    pub options: yaml_serde::Value,
    /// The recipe file's line that names the pass (1-based; 0 when not from a file).
    #[serde(skip, default)]
    pub line: usize,
    /// The base recipe that wrote the pass; empty for the recipe's own passes.
    #[serde(skip, default)]
    pub base: String,
}

impl PassSpec {
    pub fn new(name: &str, options: yaml_serde::Value) -> PassSpec {
        PassSpec { name: name.to_string(), options, line: 0, base: String::new() }
    }

    /// Where the recipe names it, for errors: "line 12: recover" or "line 9 of base detect-lossless: dce".
    pub fn at(&self) -> String {
        match (self.line, self.base.is_empty()) {
            (0, _) => format!("pass {}", self.name),
            (l, true) => format!("line {l}: {}", self.name),
            (l, false) => format!("line {l} of base {}: {}", self.base, self.name),
        }
    }
}

/// The recipes under `passes/`, built in: a recipe's `base:` names one of them when no file of
/// that name lies beside it, and `bench` and `ship` run them.
pub const SHIPPED: &[(&str, &str)] = &[
    ("identity", include_str!("../../passes/identity.yaml")),
    ("detect-cut", include_str!("../../passes/detect-cut.yaml")),
    ("detect-lossless", include_str!("../../passes/detect-lossless.yaml")),
    ("detect-f32", include_str!("../../passes/detect-f32.yaml")),
    ("detect-fp16", include_str!("../../passes/detect-fp16.yaml")),
    ("detect-int8", include_str!("../../passes/detect-int8.yaml")),
    ("detect-int8-learned", include_str!("../../passes/detect-int8-learned.yaml")),
    ("detect-int8-qat", include_str!("../../passes/detect-int8-qat.yaml")),
    ("detect-int8-robust", include_str!("../../passes/detect-int8-robust.yaml")),
    ("detect-pruned-f32", include_str!("../../passes/detect-pruned-f32.yaml")),
    ("detect-pruned-fp16", include_str!("../../passes/detect-pruned-fp16.yaml")),
    ("detect-pruned-int8", include_str!("../../passes/detect-pruned-int8.yaml")),
    ("detect-pruned-int8-qat", include_str!("../../passes/detect-pruned-int8-qat.yaml")),
    ("detect-pruned-f32-norecover", include_str!("../../passes/detect-pruned-f32-norecover.yaml")),
    ("detect-pruned-fp16-norecover", include_str!("../../passes/detect-pruned-fp16-norecover.yaml")),
    ("detect-pruned-int8-norecover", include_str!("../../passes/detect-pruned-int8-norecover.yaml")),
    ("detect-rknn", include_str!("../../passes/detect-rknn.yaml")),
    ("detect-rknn-qat", include_str!("../../passes/detect-rknn-qat.yaml")),
    ("detect-pruned-rknn", include_str!("../../passes/detect-pruned-rknn.yaml")),
    ("detect-pruned-rknn-norecover", include_str!("../../passes/detect-pruned-rknn-norecover.yaml")),
];

/// The text of a shipped recipe.
pub fn shipped(name: &str) -> Option<&'static str> {
    SHIPPED.iter().find(|(n, _)| *n == name).map(|(_, t)| *t)
}

/// How deep bases may nest: deeper is a cycle or a mistake.
const MAX_BASE_DEPTH: usize = 8;

#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Recipe {
    pub name: String,
    pub description: String,
    /// The recipes it was expanded from, nearest first (the record; `passes` holds them all).
    #[serde(skip, default)]
    pub bases: Vec<String>,
    pub passes: Vec<PassSpec>,
}

impl Recipe {
    /// A recipe file; `base:` names a sibling file, else a shipped recipe.
    pub fn load(path: &Path) -> Result<Recipe> {
        let text = std::fs::read_to_string(path).with_context(|| format!("cannot read pipeline {}", path.display()))?;
        let dir = path.parent().map(Path::to_path_buf).unwrap_or_default();
        let find = |name: &str| -> Result<String> {
            let file = dir.join(format!("{name}.yaml"));
            if file.is_file() {
                return std::fs::read_to_string(&file).with_context(|| format!("cannot read base {}", file.display()));
            }
            shipped(name).map(str::to_string).ok_or_else(|| anyhow!("base '{name}': no {} and no shipped recipe of that name", file.display()))
        };
        Recipe::parse_with(&text, &find, 0).with_context(|| format!("pipeline {}", path.display()))
    }

    /// A recipe's text; `base:` names a shipped recipe.
    pub fn parse(text: &str) -> Result<Recipe> {
        let find = |name: &str| shipped(name).map(str::to_string).ok_or_else(|| anyhow!("base '{name}': no shipped recipe of that name (shipped: {})", SHIPPED.iter().map(|r| r.0).collect::<Vec<_>>().join(", ")));
        Recipe::parse_with(text, &find, 0)
    }

    fn parse_with(text: &str, find: &dyn Fn(&str) -> Result<String>, depth: usize) -> Result<Recipe> {
        let doc: yaml_serde::Value = yaml_serde::from_str(text).map_err(|e| anyhow!("not valid YAML: {e}"))?;
        let map = doc.as_mapping().ok_or_else(|| anyhow!("expected a mapping with `name` and `passes`"))?;
        let text_field = |k: &str| map.get(k).and_then(|v| v.as_str()).unwrap_or_default().to_string();
        for key in map.keys() {
            let k = key.as_str().unwrap_or_default();
            if !["name", "description", "base", "without", "passes"].contains(&k) {
                bail!("unknown key '{k}' (expected name, description, base, without, passes)");
            }
        }
        let own = match map.get("passes") {
            None | Some(yaml_serde::Value::Null) => Vec::new(),
            Some(yaml_serde::Value::Sequence(items)) => {
                let lines = pass_lines(text, items.len());
                items.iter().zip(lines).map(|(item, line)| Ok(PassSpec { line, ..pass_spec(item)? })).collect::<Result<_>>()?
            }
            Some(_) => bail!("`passes` must be a list"),
        };
        let without: Vec<String> = match map.get("without") {
            None => Vec::new(),
            Some(v) => yaml_serde::from_value(v.clone()).map_err(|_| anyhow!("`without` must be a list of pass names"))?,
        };
        let (mut passes, mut bases) = (Vec::new(), Vec::new());
        match map.get("base") {
            None => {
                if !without.is_empty() {
                    bail!("`without` removes passes of a base: add `base:`");
                }
            }
            Some(b) => {
                let base = b.as_str().ok_or_else(|| anyhow!("`base` must be a recipe name"))?;
                // A name, never a path: a recipe cannot reach files outside its own folder.
                if base.is_empty() || base.starts_with('.') || base.contains(['/', '\\']) {
                    bail!("base '{base}': give a recipe's name (like detect-f32), not a path");
                }
                if depth >= MAX_BASE_DEPTH {
                    bail!("base '{base}': bases nest deeper than {MAX_BASE_DEPTH} (a cycle?)");
                }
                let parent = Recipe::parse_with(&find(base)?, find, depth + 1).with_context(|| format!("base {base}"))?;
                for w in &without {
                    if !parent.passes.iter().any(|p| &p.name == w) {
                        bail!("`without: [{w}]`: base {base} has no pass {w}");
                    }
                }
                bases.push(base.to_string());
                bases.extend(parent.bases);
                passes.extend(parent.passes.into_iter().filter(|p| !without.contains(&p.name)).map(|p| PassSpec { base: if p.base.is_empty() { base.to_string() } else { p.base }, ..p }));
            }
        }
        passes.extend(own);
        Ok(Recipe { name: text_field("name"), description: text_field("description"), bases, passes })
    }

    /// The recipe file form, which [`Recipe::parse`] reads back.
    pub fn to_yaml(&self) -> Result<String> {
        use yaml_serde::{Mapping, Value};
        let passes = self
            .passes
            .iter()
            .map(|p| match &p.options {
                Value::Null => Value::String(p.name.clone()),
                o => Value::Mapping(Mapping::from_iter([(Value::String(p.name.clone()), o.clone())])),
            })
            .collect();
        let doc = Mapping::from_iter([
            (Value::String("name".into()), Value::String(self.name.clone())),
            (Value::String("description".into()), Value::String(self.description.clone())),
            (Value::String("passes".into()), Value::Sequence(passes)),
        ]);
        Ok(yaml_serde::to_string(&doc)?)
    }
}

impl Recipe {
    /// The shipped `detect-lossless`: the lossless passes the detect recipes start from.
    pub fn lossless() -> Recipe {
        Recipe::parse(shipped("detect-lossless").expect("detect-lossless is shipped")).expect("the shipped detect-lossless parses")
    }

    /// The recipe with the passes `scene` asks for (drop-classes, drop-strides, crop-roi, in
    /// that order) inserted where they belong (the crop without halos when the recipe prunes).
    /// No recovery is added after a crop: with its halos the crop agrees better without it
    /// (8 minutes on physics frames took the v5 from 0.980 to 0.963 and the tiny from 0.886
    /// to 0.844, and left the v8 at 0.980).
    pub fn with_scene(&self, scene: &crate::scene::Scene) -> Result<Recipe> {
        let wanted: Vec<&str> = [("drop-classes", scene.classes.is_some()), ("drop-strides", scene.object_px.is_some()), ("crop-roi", scene.roi.is_some())]
            .into_iter()
            .filter(|p| p.1)
            .map(|p| p.0)
            .collect();
        // A recipe that places scene passes itself keeps its placement.
        if self.passes.iter().any(|p| ["drop-classes", "drop-strides", "crop-roi"].contains(&p.name.as_str())) {
            return Ok(self.clone());
        }
        // The lossless passes change nothing a scene specialization depends on: the scene
        // passes go after the longest run of them that opens a recipe (constants and gates
        // folded), before pruning, quantization and target legalization, which then work on
        // the smaller model.
        let lossless: Vec<String> = Recipe::lossless().passes.into_iter().map(|p| p.name).collect();
        let at = self.passes.iter().position(|p| !lossless.contains(&p.name)).unwrap_or(self.passes.len());
        if !self.passes[..at].iter().any(|p| p.name == "fold-constants") && !wanted.is_empty() {
            bail!("scene specialization needs constant decode shapes: the pipeline must run fold-constants before {}", self.passes.get(at).map_or("its end", |p| p.name.as_str()));
        }
        // Before pruning the crop keeps zero padding: pruning cannot follow a halo's 1x1
        // convolution between a value's channels (the v5 w0.25 with all three keys
        // pruned to 0.90x of the crop instead of 0.28x), and the pruned recipe's recovery
        // distills the crop from the full model anyway.
        let prunes = self.passes.iter().any(|p| p.name == "prune");
        let options = |n: &str| if n == "crop-roi" && prunes { yaml_serde::from_str("{halo: zero}") } else { Ok(yaml_serde::Value::Null) };
        let inserted = wanted.iter().map(|n| Ok(PassSpec::new(n, options(n)?))).collect::<Result<Vec<_>>>()?;
        let mut out = self.clone();
        out.passes.splice(at..at, inserted);
        Ok(out)
    }
}

/// The lines naming each of `n` passes: the block list's `- ` items after `passes:`, or the
/// `passes:` line itself for a flow list (`passes: [a, b]`).
fn pass_lines(text: &str, n: usize) -> Vec<usize> {
    let lines: Vec<&str> = text.lines().collect();
    let Some(at) = lines.iter().position(|l| l.starts_with("passes:")) else { return vec![0; n] };
    let items: Vec<usize> = lines.iter().enumerate().skip(at + 1).filter(|(_, l)| l.trim_start().starts_with("- ")).map(|(i, _)| i + 1).collect();
    if items.len() == n { items } else { vec![at + 1; n] }
}

fn pass_spec(item: &yaml_serde::Value) -> Result<PassSpec> {
    match item {
        yaml_serde::Value::String(s) => Ok(PassSpec::new(s, yaml_serde::Value::Null)),
        yaml_serde::Value::Mapping(m) if m.len() == 1 => {
            let (k, v) = m.iter().next().expect("one entry");
            let name = k.as_str().ok_or_else(|| anyhow!("a pass name must be a string"))?;
            Ok(PassSpec::new(name, v.clone()))
        }
        _ => bail!("each pass must be a name or `name: {{options}}`"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_both_pass_forms() {
        let r = Recipe::parse("name: x\npasses:\n  - dce\n  - prune: {ratio: 0.5}\n").unwrap();
        assert_eq!(r.passes.len(), 2);
        assert_eq!(r.passes[1].name, "prune");
        assert_eq!(r.passes[1].options.get("ratio").and_then(|v| v.as_f64()), Some(0.5));
        assert_eq!((r.passes[0].line, r.passes[1].line), (3, 4), "the lines naming them");
        assert!(Recipe::parse("name: x\npases: []\n").is_err());
        assert!(Recipe::parse("passes: 3\n").is_err());
        let again = Recipe::parse(&r.to_yaml().unwrap()).unwrap();
        assert_eq!((again.passes[0].name.as_str(), again.passes[1].options.get("ratio").and_then(|v| v.as_f64())), ("dce", Some(0.5)));
    }

    #[test]
    fn a_scene_crop_gets_halos_unless_the_recipe_prunes() {
        let scene = crate::scene::Scene { roi: Some(crate::scene::Roi { x: 0, y: 64, w: 256, h: 128 }), ..Default::default() };
        let plain = Recipe::parse("name: x\npasses: [fold-constants, dce, quantize]\n").unwrap().with_scene(&scene).unwrap();
        let names: Vec<&str> = plain.passes.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(names, ["fold-constants", "dce", "crop-roi", "quantize"], "no recovery added after a crop");
        assert!(plain.passes[2].options.is_null(), "the crop keeps its default halos");
        let pruned = Recipe::parse("name: x\npasses: [fold-constants, dce, prune, recover]\n").unwrap().with_scene(&scene).unwrap();
        assert_eq!(pruned.passes[2].name, "crop-roi");
        assert_eq!(pruned.passes[2].options.get("halo").and_then(|v| v.as_str()), Some("zero"));
    }
}
