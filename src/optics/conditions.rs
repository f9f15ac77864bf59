//! Stress conditions: parameterized transforms of the frames (and of the blur map a model
//! that takes one is given) where uncooled LWIR deployments break. A condition file lists
//! kinds with their parameters; a list of values is a sweep, one condition per value.
//!
//! ```yaml
//! frames: 32
//! conditions:
//!   - {kind: noise, q: [10, 200], sigma: 2}
//!   - {kind: hot_objects, count: 3, size_px: 16}
//! ```

use crate::optics::blur_map::BlurMap;
use crate::optics::degrade::{add_noise, NoiseModel, FULL_SCALE_14BIT};
use crate::optics::rng::Rng;
use anyhow::{anyhow, bail, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The shipped set, compiled in so `stress` works from any folder.
const DEFAULT_SET: &str = include_str!("../../passes/stress.yaml");
/// The lens whose map `other_lens` gives by default: the multi-element LWIR design.
const OTHER_LENS: &str = include_str!("../../calib/lens_multi_lwir.yaml");

/// Conditions one file may expand to: a sweep of thousands is a typo, and each costs a pass
/// over every frame and candidate.
const MAX_CONDITIONS: usize = 256;

/// One value or a sweep of values.
#[derive(Clone, Debug, Deserialize)]
#[serde(untagged)]
pub enum Sweep {
    One(f64),
    Many(Vec<f64>),
}

impl Sweep {
    fn values(&self) -> Vec<f64> {
        match self {
            Sweep::One(v) => vec![*v],
            Sweep::Many(v) => v.clone(),
        }
    }
}

fn default_sigma() -> f64 {
    2.0
}
fn default_count() -> usize {
    3
}
fn default_cluster() -> usize {
    3
}

/// What a condition does; `T` is `Sweep` as written in a file, `f64` once expanded.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum Kind<T> {
    /// The frames as given: the baseline every other condition is read against.
    Clean,
    /// The paper's detector model on top of the frames: I = (floor(I/q) + eps) q with
    /// eps ~ N(0, sigma^2), q in counts of a 14-bit detector (10: high SNR, 200: worse than
    /// the training frames' 90).
    Noise {
        q: T,
        #[serde(default = "default_sigma")]
        sigma: f64,
    },
    /// Gain drift: every pixel times `gain`, clipped at full scale.
    Gain { gain: T },
    /// Offset drift (fraction of full scale), clipped to [0, 1].
    Offset { offset: T },
    /// `count` saturated discs of `size_px` diameter: hot engines at the top of the range.
    HotObjects {
        #[serde(default = "default_count")]
        count: usize,
        size_px: T,
    },
    /// Towards black: v * level (cold sky filling the frame).
    Dark { level: T },
    /// Towards white: 1 - (1 - v) * level (a hot scene near saturation).
    Bright { level: T },
    /// Clusters of dead (zero) pixels covering `share` of the frame.
    DeadPixels {
        share: T,
        #[serde(default = "default_cluster")]
        cluster: usize,
    },
    /// Clusters of pixels stuck at full scale covering `share` of the frame.
    StuckPixels {
        share: T,
        #[serde(default = "default_cluster")]
        cluster: usize,
    },
    /// Fixed-pattern noise: a Gaussian offset per row and per column, `sigma` of full scale.
    RowColumnNoise { sigma: T },
    /// The camera's blur map plus `delta` (clipped to [0, 1]) where the model was compiled with the map as given.
    BlurOffset { delta: T },
    /// The camera's blur map shifted by `regions` columns (edge replicated): a decentred lens.
    BlurShift { regions: T },
    /// The blur map of another lens (a lens YAML; the built-in multi-element LWIR design by default).
    OtherLens {
        #[serde(default)]
        lens: Option<PathBuf>,
    },
    /// `share` of the pixels NaN (a broken readout or a bad decode upstream).
    NanPixels { share: T },
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    frames: Option<usize>,
    conditions: Vec<Kind<Sweep>>,
}

/// One expanded condition.
#[derive(Clone, Debug)]
pub struct Condition {
    pub name: String,
    pub kind: Kind<f64>,
    /// For `other_lens`: that lens's simulated blur map.
    pub blur: Option<BlurMap>,
}

pub struct ConditionSet {
    pub conditions: Vec<Condition>,
    /// Frames per condition the file asks for.
    pub frames: Option<usize>,
    pub source: String,
}

/// The conditions of `path`, or the shipped set (`passes/stress.yaml`).
pub fn load(path: Option<&Path>) -> Result<ConditionSet> {
    let (text, source) = match path {
        Some(p) => (std::fs::read_to_string(p).with_context(|| format!("cannot read condition file {}", p.display()))?, p.display().to_string()),
        None => (DEFAULT_SET.to_string(), "the shipped set (passes/stress.yaml)".to_string()),
    };
    let base = path.and_then(Path::parent).unwrap_or(Path::new("."));
    let mut set = parse(&text, base).map_err(|e| anyhow!("condition file {source}: {e}"))?;
    set.source = source;
    Ok(set)
}

/// Conditions from YAML text; lens files resolve against `base`.
pub fn parse(text: &str, base: &Path) -> Result<ConditionSet> {
    let file: File = yaml_serde::from_str(text)?;
    if file.conditions.is_empty() {
        bail!("no conditions listed; add at least one, e.g. - {{kind: clean}}");
    }
    if file.frames == Some(0) || file.frames.is_some_and(|n| n > 4096) {
        bail!("frames must be in 1..4096");
    }
    let mut conditions: Vec<Condition> = Vec::new();
    for spec in &file.conditions {
        for kind in expand(spec) {
            validate(&kind)?;
            let blur = match &kind {
                Kind::OtherLens { lens } => Some(other_lens_map(lens.as_ref().map(|l| base.join(l)).as_deref())?),
                _ => None,
            };
            let name = name(&kind, blur.as_ref().map(|_| lens_name(&kind, base)).transpose()?.as_deref());
            if conditions.iter().any(|c| c.name == name) {
                bail!("'{name}' is listed twice");
            }
            if conditions.len() >= MAX_CONDITIONS {
                bail!("more than {MAX_CONDITIONS} conditions (sweeps included); split the file");
            }
            conditions.push(Condition { name, kind, blur });
        }
    }
    Ok(ConditionSet { conditions, frames: file.frames, source: String::new() })
}

/// Conditions chosen by name from the shipped set (for `quantize: {calib_conditions: [...]}`).
pub fn by_name(names: &[String]) -> Result<Vec<Condition>> {
    let all = load(None)?.conditions;
    names
        .iter()
        .map(|n| {
            all.iter().find(|c| &c.name == n).cloned().ok_or_else(|| {
                let known: Vec<&str> = all.iter().map(|c| c.name.as_str()).collect();
                anyhow!("no stress condition '{n}' in the shipped set; pick from {}", known.join(", "))
            })
        })
        .collect()
}

fn expand(spec: &Kind<Sweep>) -> Vec<Kind<f64>> {
    use Kind::*;
    let each = |s: &Sweep, f: &dyn Fn(f64) -> Kind<f64>| s.values().into_iter().map(f).collect::<Vec<_>>();
    match spec {
        Clean => vec![Clean],
        Noise { q, sigma } => each(q, &|q| Noise { q, sigma: *sigma }),
        Gain { gain } => each(gain, &|gain| Gain { gain }),
        Offset { offset } => each(offset, &|offset| Offset { offset }),
        HotObjects { count, size_px } => each(size_px, &|size_px| HotObjects { count: *count, size_px }),
        Dark { level } => each(level, &|level| Dark { level }),
        Bright { level } => each(level, &|level| Bright { level }),
        DeadPixels { share, cluster } => each(share, &|share| DeadPixels { share, cluster: *cluster }),
        StuckPixels { share, cluster } => each(share, &|share| StuckPixels { share, cluster: *cluster }),
        RowColumnNoise { sigma } => each(sigma, &|sigma| RowColumnNoise { sigma }),
        BlurOffset { delta } => each(delta, &|delta| BlurOffset { delta }),
        BlurShift { regions } => each(regions, &|regions| BlurShift { regions }),
        OtherLens { lens } => vec![OtherLens { lens: lens.clone() }],
        NanPixels { share } => each(share, &|share| NanPixels { share }),
    }
}

fn validate(k: &Kind<f64>) -> Result<()> {
    use Kind::*;
    let within = |what: &str, v: f64, lo: f64, hi: f64| -> Result<()> {
        if !(lo..=hi).contains(&v) {
            bail!("{what} {v} is outside {lo}..{hi}");
        }
        Ok(())
    };
    match k {
        Clean | OtherLens { .. } => Ok(()),
        Noise { q, sigma } => within("noise q", *q, 1e-3, 1e4).and(within("noise sigma", *sigma, 0.0, 100.0)),
        Gain { gain } => within("gain", *gain, 1e-3, 100.0),
        Offset { offset } => within("offset", *offset, -1.0, 1.0),
        HotObjects { count, size_px } => within("hot_objects count", *count as f64, 1.0, 100.0).and(within("hot_objects size_px", *size_px, 1.0, 1024.0)),
        Dark { level } | Bright { level } => within("level", *level, 0.0, 1.0),
        DeadPixels { share, cluster } | StuckPixels { share, cluster } => within("share", *share, 0.0, 0.5).and(within("cluster", *cluster as f64, 1.0, 64.0)),
        RowColumnNoise { sigma } => within("row_column_noise sigma", *sigma, 0.0, 1.0),
        BlurOffset { delta } => within("blur_offset delta", *delta, -1.0, 1.0),
        BlurShift { regions } => within("blur_shift regions", *regions, -16.0, 16.0).and(if regions.fract() == 0.0 { Ok(()) } else { bail!("blur_shift regions {regions} is not a whole number") }),
        NanPixels { share } => within("nan_pixels share", *share, 0.0, 1.0),
    }
}

fn lens_name(k: &Kind<f64>, base: &Path) -> Result<String> {
    Ok(match k {
        Kind::OtherLens { lens: Some(p) } => crate::optics::lens::Lens::load(&base.join(p))?.name,
        _ => yaml_serde::from_str::<crate::optics::lens::Lens>(OTHER_LENS).map_err(|e| anyhow!("built-in lens: {e}"))?.name,
    })
}

/// A short stable name: the kind and its swept value.
fn name(k: &Kind<f64>, lens: Option<&str>) -> String {
    use Kind::*;
    let pct = |s: f64| format!("{}%", (s * 1e5).round() / 1e3);
    match k {
        Clean => "clean".into(),
        Noise { q, .. } => format!("noise_q{q}"),
        Gain { gain } => format!("gain_x{gain}"),
        Offset { offset } => format!("offset_{offset:+}"),
        HotObjects { size_px, .. } => format!("hot_objects_{size_px}px"),
        Dark { level } => format!("dark_x{level}"),
        Bright { level } => format!("bright_{level}"),
        DeadPixels { share, .. } => format!("dead_pixels_{}", pct(*share)),
        StuckPixels { share, .. } => format!("stuck_pixels_{}", pct(*share)),
        RowColumnNoise { sigma } => format!("row_column_noise_{sigma}"),
        BlurOffset { delta } => format!("blur_{delta:+}"),
        BlurShift { regions } => format!("blur_shift_{regions}"),
        OtherLens { .. } => {
            let slug: String = lens.unwrap_or("lens").chars().map(|c| if c.is_ascii_alphanumeric() { c.to_ascii_lowercase() } else { '_' }).collect();
            format!("other_lens_{}", slug.trim_matches('_'))
        }
        NanPixels { share } => format!("nan_pixels_{}", pct(*share)),
    }
}

fn other_lens_map(lens: Option<&Path>) -> Result<BlurMap> {
    use crate::optics::{blur_index, lens::Lens, psf, psf_set::PsfSet};
    let lens: Lens = match lens {
        Some(p) => Lens::load(p)?,
        None => yaml_serde::from_str(OTHER_LENS).map_err(|e| anyhow!("built-in lens: {e}"))?,
    };
    // The grid and kernel of `psf simulate`'s defaults (those the shipped maps were made with).
    let (rows, cols, k) = (6, 8, 31);
    let (_, kernels) = psf::simulate(&lens, rows, cols, k);
    let set = PsfSet { rows, cols, k, kernels };
    Ok(blur_index::blur_map(&set.stats(), rows, cols))
}

impl Condition {
    /// Whether the condition changes the blur map rather than the frames.
    pub fn changes_blur(&self) -> bool {
        matches!(self.kind, Kind::BlurOffset { .. } | Kind::BlurShift { .. } | Kind::OtherLens { .. })
    }

    /// The blur map a model taking one is given under this condition.
    pub fn blur_map(&self, base: &BlurMap) -> BlurMap {
        let mut m = base.clone();
        match &self.kind {
            Kind::BlurOffset { delta } => m.values.iter_mut().for_each(|v| *v = (*v + *delta as f32).clamp(0.0, 1.0)),
            Kind::BlurShift { regions } => {
                let r = *regions as i64;
                for row in 0..m.rows {
                    for col in 0..m.cols {
                        let from = (col as i64 - r).clamp(0, m.cols as i64 - 1) as usize;
                        m.values[row * m.cols + col] = base.values[row * base.cols + from];
                    }
                }
            }
            Kind::OtherLens { .. } => {
                let other = self.blur.as_ref().expect("other_lens carries its map");
                // Nearest region where the grids differ.
                for row in 0..m.rows {
                    for col in 0..m.cols {
                        let (r, c) = (row * other.rows / m.rows, col * other.cols / m.cols);
                        m.values[row * m.cols + col] = other.values[r * other.cols + c];
                    }
                }
            }
            _ => {}
        }
        m
    }

    /// A [1, 1, H, W] image under this condition, seeded.
    pub fn apply_tensor(&self, t: &crate::tensor::Tensor, seed: u64) -> crate::tensor::Tensor {
        let (h, w) = (t.shape[t.shape.len() - 2], t.shape[t.shape.len() - 1]);
        let mut data = t.as_f32().map_or_else(|| t.data.to_f64().into_iter().map(|v| v as f32).collect(), <[f32]>::to_vec);
        for plane in data.chunks_mut(h * w) {
            self.apply(plane, h, w, &mut Rng::new(seed));
        }
        crate::tensor::Tensor::f32(t.shape.clone(), data)
    }

    /// Applies the condition to one `h x w` frame (values in [0, 1]) in place.
    pub fn apply(&self, img: &mut [f32], h: usize, w: usize, rng: &mut Rng) {
        use Kind::*;
        match &self.kind {
            Clean | BlurOffset { .. } | BlurShift { .. } | OtherLens { .. } => {}
            Noise { q, sigma } => add_noise(img, &NoiseModel { q: *q, sigma: *sigma, full_scale: FULL_SCALE_14BIT }, rng),
            Gain { gain } => img.iter_mut().for_each(|v| *v = (*v * *gain as f32).clamp(0.0, 1.0)),
            Offset { offset } => img.iter_mut().for_each(|v| *v = (*v + *offset as f32).clamp(0.0, 1.0)),
            Dark { level } => img.iter_mut().for_each(|v| *v *= *level as f32),
            Bright { level } => img.iter_mut().for_each(|v| *v = 1.0 - (1.0 - *v) * *level as f32),
            HotObjects { count, size_px } => {
                let r = size_px / 2.0;
                for _ in 0..*count {
                    let (cx, cy) = (rng.range(0.0, w as f64), rng.range(0.0, h as f64));
                    for y in (cy - r).floor().max(0.0) as usize..((cy + r).ceil() as usize).min(h) {
                        for x in (cx - r).floor().max(0.0) as usize..((cx + r).ceil() as usize).min(w) {
                            if (x as f64 + 0.5 - cx).powi(2) + (y as f64 + 0.5 - cy).powi(2) <= r * r {
                                img[y * w + x] = 1.0;
                            }
                        }
                    }
                }
            }
            DeadPixels { share, cluster } => clusters(img, h, w, *share, *cluster, 0.0, rng),
            StuckPixels { share, cluster } => clusters(img, h, w, *share, *cluster, 1.0, rng),
            RowColumnNoise { sigma } => {
                let rows: Vec<f32> = (0..h).map(|_| (sigma * rng.normal()) as f32).collect();
                let cols: Vec<f32> = (0..w).map(|_| (sigma * rng.normal()) as f32).collect();
                for y in 0..h {
                    for x in 0..w {
                        img[y * w + x] = (img[y * w + x] + rows[y] + cols[x]).clamp(0.0, 1.0);
                    }
                }
            }
            NanPixels { share } => {
                let n = ((share * (h * w) as f64).round() as usize).max(1);
                for _ in 0..n {
                    img[(rng.next_u64() % (h * w) as u64) as usize] = f32::NAN;
                }
            }
        }
    }
}

/// Square clusters of `side` pixels set to `value`, as many as cover `share` of the frame.
fn clusters(img: &mut [f32], h: usize, w: usize, share: f64, side: usize, value: f32, rng: &mut Rng) {
    let n = ((share * (h * w) as f64 / (side * side) as f64).round() as usize).max(1);
    for _ in 0..n {
        let (y0, x0) = ((rng.next_u64() % h as u64) as usize, (rng.next_u64() % w as u64) as usize);
        for y in y0..(y0 + side).min(h) {
            for x in x0..(x0 + side).min(w) {
                img[y * w + x] = value;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_set_expands_sweeps_into_named_conditions() {
        let set = load(None).unwrap();
        let names: Vec<&str> = set.conditions.iter().map(|c| c.name.as_str()).collect();
        assert!(set.conditions.len() >= 10, "{names:?}");
        assert!(names.contains(&"clean") && names.contains(&"noise_q200") && names.contains(&"gain_x2"), "{names:?}");
    }

    #[test]
    fn unknown_keys_and_out_of_range_values_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        for (text, says) in [("conditions: [{kind: gain, gian: 2}]", "gian"), ("conditions: [{kind: gain, gain: -1}]", "outside"), ("conditions: [{kind: fog}]", "fog"), ("conditions: []", "no conditions")] {
            let p = dir.path().join("c.yaml");
            std::fs::write(&p, text).unwrap();
            let e = load(Some(&p)).err().expect(text).to_string();
            assert!(e.contains(says), "{text}: {e}");
        }
    }

    #[test]
    fn transforms_do_what_they_say() {
        let (h, w) = (32, 40);
        let frame: Vec<f32> = (0..h * w).map(|i| 0.2 + 0.5 * (i % 7) as f32 / 7.0).collect();
        let run = |k: Kind<f64>| {
            let mut v = frame.clone();
            Condition { name: String::new(), kind: k, blur: None }.apply(&mut v, h, w, &mut Rng::new(1));
            v
        };
        assert!(run(Kind::Gain { gain: 2.0 }).iter().zip(&frame).all(|(a, b)| *a == (2.0 * b).min(1.0)));
        assert!(run(Kind::HotObjects { count: 2, size_px: 6.0 }).iter().filter(|&&v| v == 1.0).count() >= 20);
        let dead = run(Kind::DeadPixels { share: 0.05, cluster: 2 }).iter().filter(|&&v| v == 0.0).count();
        assert!((40..=70).contains(&dead), "{dead} dead pixels for 5% of 1280");
        assert_eq!(run(Kind::NanPixels { share: 0.01 }).iter().filter(|v| v.is_nan()).count(), 13);
        assert!(run(Kind::Dark { level: 0.1 }).iter().all(|&v| v <= 0.07));
        let base = BlurMap { rows: 2, cols: 3, values: vec![0.0, 0.5, 1.0, 0.1, 0.2, 0.3] };
        let shifted = Condition { name: String::new(), kind: Kind::BlurShift { regions: 1.0 }, blur: None }.blur_map(&base);
        assert_eq!(shifted.values, vec![0.0, 0.0, 0.5, 0.1, 0.1, 0.2]);
    }
}
