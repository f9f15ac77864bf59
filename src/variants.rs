//! What `bench` and `ship` share: compiling a model's variants side by side (a variant that
//! fails its hard limit is set aside with those made from it), the shipped recipes they
//! compile and the one-pass recipes cut from them, a recovery budget laid over a recipe, and
//! timing every variant in one interleaved loop so that their ratios come from the same run.

use crate::compile::CompileReport;
use crate::pipeline::Recipe;
use crate::runtime::{self, op_profile::{self, OpProfile}, Engine, Runtime};
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};
use std::path::{Path, PathBuf};

/// A shipped recipe's text (`passes/NAME.yaml`, built in).
pub fn recipe(name: &str) -> &'static str {
    crate::pipeline::recipe::shipped(name).unwrap_or_else(|| panic!("{name} is a shipped recipe"))
}

/// The variants whose compile ended past a lossy pass's hard limit (no artifact), and why; a
/// variant made from a failed one fails with it. `bench` and `ship` go on with the rest.
#[derive(Default)]
pub struct Failed(Vec<(String, String)>);

impl Failed {
    pub fn contains(&self, name: &str) -> bool {
        self.0.iter().any(|(n, _)| n == name)
    }

    /// True (and recorded) when `name`'s source variant failed.
    pub fn source_failed(&mut self, name: &str, from: Option<&str>) -> bool {
        let Some(f) = from.filter(|f| self.contains(f)) else { return false };
        self.0.push((name.to_string(), format!("its source variant {f} failed")));
        true
    }

    /// The compile's report, or None when it failed its hard limit (recorded, and said on
    /// stderr under `command`); other errors pass through.
    pub fn take(&mut self, command: &str, name: &str, compiled: Result<CompileReport>) -> Result<Option<CompileReport>> {
        match compiled {
            Ok(r) => Ok(Some(r)),
            Err(e) if crate::pipeline::is_quality_failure(&e) => {
                eprintln!("{command}: {name} failed: {e:#}");
                self.0.push((name.to_string(), format!("{e:#}")));
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }

    /// `name: why`, one a variant, for the reports.
    pub fn lines(self) -> Vec<String> {
        self.0.into_iter().map(|(n, why)| format!("{n}: {why}")).collect()
    }
}

/// A recipe of the passes `text` adds to its base, named `name`: applied to the base's
/// output, it compiles what the whole recipe does (e.g. INT8 and the narrow convolutions'
/// form from the pruned f32 compile) without training the same model again.
pub fn own_passes_of(text: &str, name: &str) -> Result<String> {
    let r = Recipe::parse(text)?;
    let own: Vec<_> = r.passes.iter().filter(|p| p.base.is_empty()).cloned().collect();
    if own.is_empty() {
        anyhow::bail!("built-in recipe {} adds no passes to its base", r.name);
    }
    Recipe { name: name.into(), description: format!("the passes {} adds to its base", r.name), bases: Vec::new(), passes: own }.to_yaml()
}

/// A recipe of `text`'s last pass alone, named `name`: applied to an earlier variant, it
/// makes e.g. INT8 from the f32 compile without running the lossless passes again.
pub fn last_pass_of(text: &str, name: &str) -> Result<String> {
    let r = Recipe::parse(text)?;
    let last = r.passes.last().cloned().ok_or_else(|| anyhow!("built-in recipe {} has no passes", r.name))?;
    Recipe { name: name.into(), description: format!("the last pass of {}", r.name), bases: Vec::new(), passes: vec![last] }.to_yaml()
}

/// `text` with its recovery's total step budget set to `steps` (unchanged when None), shared
/// among its `recover` passes in the recipe's own proportions (a recipe that prunes in stages
/// recovers after each). A pass that names its frames and is given fewer steps than its own
/// trains on proportionally fewer, never fewer than the pass's default or the frames its steps
/// draw, whichever is less (nor more than it asked for): a recipe's frame count is sized for
/// its own steps, a recovery of a tenth of them sees a tenth of the frames, and drawing the
/// rest cost 26 s of a 2-minute demo on 2 cores. A frame past its steps' batches is never
/// trained on: 8 steps of 8 drew 512 frames, and their teacher outputs took half the recovery.
pub fn with_recover_steps(text: &str, steps: Option<usize>) -> Result<String> {
    let Some(steps) = steps else { return Ok(text.to_string()) };
    if steps == 0 {
        anyhow::bail!("--recover-steps must be at least 1");
    }
    let mut r = Recipe::parse(text)?;
    let defaults = crate::passes::recover::Options::default();
    let own = |p: &crate::pipeline::recipe::PassSpec| p.options.get("steps").and_then(|m| m.as_u64()).unwrap_or(defaults.schedule.steps as u64) as f64;
    let total: f64 = r.passes.iter().filter(|p| p.name == "recover").map(own).sum::<f64>().max(1.0);
    for p in r.passes.iter_mut().filter(|p| p.name == "recover") {
        let share = (steps as f64 * own(p) / total).round().max(1.0);
        let asked = p.options.get("frames").and_then(|f| f.as_u64());
        let mut m = match &p.options {
            yaml_serde::Value::Mapping(m) => m.clone(),
            _ => yaml_serde::Mapping::new(),
        };
        m.insert("steps".into(), (share as u64).into());
        if let Some(asked) = asked {
            let batch = p.options.get("batch").and_then(|b| b.as_u64()).unwrap_or(defaults.schedule.batch as u64) as f64;
            let floor = (share * batch).min(defaults.frames as f64);
            let fewer = (asked as f64 * share / own(p)).max(floor).min(asked as f64).round() as u64;
            m.insert("frames".into(), fewer.into());
        }
        p.options = yaml_serde::Value::Mapping(m);
    }
    r.to_yaml()
}

/// What [`time_together`] times: the original on ORT, then each (label, engine, model).
pub struct Timing<'a> {
    pub original: &'a Path,
    pub timed: &'a [(String, Engine, PathBuf)],
    /// The frame: the first of this folder, or a simulated one.
    pub data: Option<&'a Path>,
    pub psf: Option<&'a Path>,
    pub runs: usize,
    pub threads: usize,
}

/// Median milliseconds of the original on ORT, then of each timed model, all interleaved in
/// one loop on the same frame, every session on the same threads.
pub fn time_together(t: &Timing) -> Result<Vec<f64>> {
    let (reference, frame, psf) = timing_frame(t)?;
    let mut loaded: Vec<(String, Box<dyn Runtime>, Vec<(String, Tensor)>)> = Vec::new();
    let inputs = crate::verify::feeds(&reference, &frame, psf.as_ref())?;
    loaded.push(("original/ort".into(), runtime::load(Engine::Ort, &reference.model, &inputs, t.threads)?, inputs));
    for (name, engine, path) in t.timed {
        let side = crate::verify::side(path, name)?;
        let inputs = crate::verify::feeds(&side, &frame, psf.as_ref())?;
        loaded.push((format!("{name}/{engine:?}"), runtime::load(*engine, &side.model, &inputs, t.threads)?, inputs));
    }
    let mut models: Vec<(String, &mut dyn Runtime, Vec<(String, Tensor)>)> = Vec::new();
    for (n, rt, i) in loaded.iter_mut() {
        models.push((n.clone(), rt.as_mut(), std::mem::take(i)));
    }
    let latency = crate::runtime::latency::interleaved(&mut models, t.runs)?;
    Ok(latency.into_iter().map(|l| l.median_ms).collect())
}

/// The original, and the frame and blur map every timed model runs on.
fn timing_frame(t: &Timing) -> Result<(crate::verify::Side, crate::frames::Frame, Option<Tensor>)> {
    let reference = crate::verify::side(t.original, "original")?;
    let (h, w) = reference.input.shape;
    let frame = match t.data {
        Some(d) => crate::frames::load_folder(d, h, w)?.swap_remove(0),
        None => crate::frames::synthetic(1, h, w, 0).swap_remove(0),
    };
    let psf = t.psf.map(crate::verify::blur_input).transpose()?;
    Ok((reference, frame, psf))
}

/// Where the time goes in each timed model on its engine, on the frame [`time_together`]
/// times (one model after another: a profile's shares and GMAC/s are its own run's, not a
/// comparison between models).
pub fn profile_each(t: &Timing) -> Result<Vec<(String, OpProfile)>> {
    let (_, frame, psf) = timing_frame(t)?;
    let mut out = Vec::new();
    for (name, engine, path) in t.timed {
        let side = crate::verify::side(path, name)?;
        let inputs = crate::verify::feeds(&side, &frame, psf.as_ref())?;
        out.push((name.clone(), op_profile::profile(*engine, &side.model, &inputs, t.threads)?));
    }
    Ok(out)
}

/// Several artifacts on this CPU: every model on every engine timed in one interleaved loop
/// (ratios against the first model on the same engine, from the same run), then each
/// profiled per operator and layer.
#[derive(serde::Serialize)]
pub struct Comparison {
    pub threads: usize,
    pub runs: usize,
    pub rows: Vec<Compared>,
    /// For each model profiled on both engines: where tract loses to ONNX Runtime.
    pub gaps: Vec<Gap>,
}

#[derive(serde::Serialize)]
pub struct Gap {
    pub model: String,
    pub gap: crate::runtime::engine_gap::EngineGap,
}

#[derive(serde::Serialize)]
pub struct Compared {
    pub model: String,
    pub engine: Engine,
    pub median_ms: f64,
    /// Against the first model's median on the same engine.
    pub ratio: f64,
    pub macs: u64,
    pub profile: OpProfile,
}

pub fn compare(models: &[PathBuf], engines: &[Engine], data: Option<&Path>, psf: Option<&Path>, runs: usize, threads: usize) -> Result<Comparison> {
    let first = models.first().ok_or_else(|| anyhow!("give at least one model"))?;
    let timed: Vec<(String, Engine, PathBuf)> = models.iter().flat_map(|m| engines.iter().map(move |e| (m.display().to_string(), *e, m.clone()))).collect();
    let t = Timing { original: first, timed: &timed, data, psf, runs, threads };
    // The first entry is the first model on ORT, timed as the loop's reference.
    let latency = time_together(&t)?;
    let profiles = profile_each(&t)?;
    let mut rows: Vec<Compared> = Vec::new();
    for (((model, engine, _), ms), (_, profile)) in timed.iter().zip(&latency[1..]).zip(profiles) {
        let base = rows.iter().find(|r| r.engine == *engine).map_or(*ms, |r| r.median_ms);
        rows.push(Compared { model: model.clone(), engine: *engine, median_ms: *ms, ratio: ms / base, macs: profile.macs, profile });
    }
    let gaps = models
        .iter()
        .filter_map(|m| {
            let model = m.display().to_string();
            let on = |e: Engine| rows.iter().find(|r| r.model == model && r.engine == e);
            let (o, t) = (on(Engine::Ort)?, on(Engine::Tract)?);
            Some(Gap { gap: crate::runtime::engine_gap::between(&o.profile, &t.profile), model })
        })
        .collect();
    Ok(Comparison { threads, runs, rows, gaps })
}

impl Comparison {
    pub fn render(&self) -> String {
        let mut s = String::new();
        if self.rows.len() > self.rows.iter().filter(|r| r.model == self.rows[0].model).count() {
            s += &format!("interleaved, {} runs each on {} threads; ratios against the first model on the same engine\n\n", self.runs, self.threads);
            s += "  model                                               engine     ms    ratio   M MACs  MAC ratio\n";
            for r in &self.rows {
                let first = self.rows.iter().find(|x| x.engine == r.engine).expect("each engine has a first row");
                s += &format!("  {:<50} {:<6} {:>7.2} {:>7.3}x {:>8.1} {:>9.3}x\n", r.model, r.engine.as_str(), r.median_ms, r.ratio, r.macs as f64 / 1e6, r.macs as f64 / first.macs.max(1) as f64);
            }
            s += "\n";
        }
        for r in &self.rows {
            s += &format!("{}\n{}\n", r.model, r.profile.render());
        }
        for g in &self.gaps {
            s += &format!("{}\n{}\n", g.model, g.gap.render());
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recover_steps_are_shared_in_the_recipes_proportions() {
        let text = "name: t\npasses:\n  - prune: {ratio: 0.5}\n  - recover: {steps: 600, lr: 0.002, frames: 2048}\n  - prune: {ratio: 0.5}\n  - recover\n";
        let r = Recipe::parse(&with_recover_steps(text, Some(160)).unwrap()).unwrap();
        let steps: Vec<u64> = r.passes.iter().filter(|p| p.name == "recover").map(|p| p.options.get("steps").unwrap().as_u64().unwrap()).collect();
        // 600 and the default 1000 steps: 160 shared 600:1000.
        assert_eq!(steps, [60, 100]);
        assert_eq!(r.passes[1].options.get("lr").unwrap().as_f64(), Some(0.002));
        // A tenth of its steps: a tenth of 2048 frames, held at what 60 steps draw (at most the
        // default 512); the default stays unset.
        let batch = crate::passes::recover::Options::default().schedule.batch as u64;
        assert_eq!(r.passes[1].options.get("frames").unwrap().as_u64(), Some((60 * batch).min(512)));
        let shipped = "name: t\npasses:\n  - recover: {steps: 8000, batch: 8, frames: 4096}\n";
        let frames = |steps| Recipe::parse(&with_recover_steps(shipped, Some(steps)).unwrap()).unwrap().passes[0].options.get("frames").unwrap().as_u64();
        assert_eq!(frames(8), Some(64), "8 steps of 8 draw 64 frames");
        assert_eq!(frames(800), Some(512), "a tenth of 4096, held at the default");
        assert!(r.passes[3].options.get("frames").is_none());
        let longer = Recipe::parse(&with_recover_steps(text, Some(16000)).unwrap()).unwrap();
        assert_eq!(longer.passes[1].options.get("frames").unwrap().as_u64(), Some(2048));
        let half = Recipe::parse(&with_recover_steps("name: t\npasses:\n  - recover: {steps: 8000, frames: 2048}\n", Some(4000)).unwrap()).unwrap();
        assert_eq!(half.passes[0].options.get("frames").unwrap().as_u64(), Some(1024));
        assert_eq!(with_recover_steps(text, None).unwrap(), text);
        assert!(with_recover_steps(text, Some(0)).is_err());
    }
}
