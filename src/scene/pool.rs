//! Global pooling over a crop: the frame's average, estimated from the ROI's.
//!
//! The PALS-Bridge's squeeze-excitation averages a feature map over the whole frame; cropped,
//! it averages over the ROI alone, and every channel's gate moves with the region left out
//! (the sky above a road is not the road). On the trained tiny v5 that difference alone, with
//! every other value exact, cost the crop a third of its disagreement (agreement 0.953).
//! Here each cropped `GlobalAveragePool` is followed by a 1x1 convolution that maps the ROI's
//! channel means to the frame's: y = W x + b, fitted on calibration frames against the full
//! model's own values by ridge regression pulled towards W = I (the ROI's mean is the frame's
//! best first guess; with 64 frames and up to 256 channels an unpulled fit would memorise).
//! The pull is chosen per pool by 4-fold cross-validation among [`LAMBDAS`] and the
//! intercept alone (W = I, the frames' average offset); the report gives each pool's choice
//! and its held-out error relative to the uncorrected crop's.
//! `halo: zero` leaves the pools as they are; `mean` keeps the offset alone.

use super::halo::{constant, node, place, Mode};
use crate::ir::{infer, Graph};
use crate::onnx::attr;
use crate::onnx::proto::{GraphProto, ModelProto};
use crate::ridge::Moments;
use crate::scene::Roi;
use anyhow::Result;

/// Ridge strengths tried, relative to the ROI means' average variance over the frames: from
/// nearly free (enough frames for the channels) to nearly the identity.
const LAMBDAS: [f64; 6] = [1e-3, 1e-2, 1e-1, 1.0, 10.0, 100.0];

/// Folds of the cross-validation: 16 held-out frames of 64 per fold.
const FOLDS: usize = 4;

#[derive(Debug, serde::Serialize)]
pub struct PoolReport {
    pub value: String,
    pub channels: usize,
    /// The chosen ridge strength; None for the intercept alone.
    pub lambda: Option<f64>,
    /// Held-out squared error of the correction relative to the uncorrected crop's (0 = exact).
    pub rel_error: f64,
}

/// One pooled value: its frame means (targets) and ROI means (features), frame by frame.
struct Samples {
    channels: usize,
    roi: Vec<Vec<f64>>,
    frame: Vec<Vec<f64>>,
}

/// The global average pools of one cropped model and their calibration means: the frame's
/// (targets) and the ROI's (features), both from the full model ([`Pools::observe_full`]);
/// [`Pools::take_means`] replaces the ROI's with what the crop computes
/// ([`super::closed_loop`]).
pub struct Pools {
    /// Per pool: its node in the cropped model and its input.
    pub nodes: Vec<(usize, String)>,
    places: Vec<super::halo::Place>,
    samples: Vec<Samples>,
}

impl Pools {
    /// No pools corrected.
    pub fn none() -> Pools {
        Pools { nodes: Vec::new(), places: Vec::new(), samples: Vec::new() }
    }

    /// Every `GlobalAveragePool` of `cropped` (the `full` model cut to `roi` of a `frame`)
    /// whose input lies on the full model's grid.
    pub fn new(cropped: &ModelProto, full: &ModelProto, roi: Roi, frame: [usize; 2]) -> Result<Pools> {
        let fg = full.graph.as_ref().ok_or_else(|| anyhow::anyhow!("the model has no graph"))?;
        let inf = infer(&Graph::build(fg)?);
        let g = cropped.graph.as_ref().ok_or_else(|| anyhow::anyhow!("the model has no graph"))?;
        let mut pools = Pools::none();
        for (i, n) in g.node.iter().enumerate().filter(|(_, n)| n.op_type == "GlobalAveragePool") {
            if let Some(p) = place(&inf, &n.input[0], roi, frame) {
                pools.nodes.push((i, n.input[0].clone()));
                pools.samples.push(Samples { channels: p.channels, roi: vec![Vec::new(); p.channels], frame: vec![Vec::new(); p.channels] });
                pools.places.push(p);
            }
        }
        Ok(pools)
    }

    /// Appends one frame's means of every pool reading `value` from `data`, its value in the
    /// full model ([1, C, H, W]).
    pub fn observe_full(&mut self, value: &str, data: &[f32]) {
        for k in (0..self.nodes.len()).filter(|&k| self.nodes[k].1 == value) {
            let p = &self.places[k];
            let (h, w) = (p.full[0], p.full[1]);
            if data.len() != p.channels * h * w {
                continue;
            }
            for c in 0..p.channels {
                let plane = &data[c * h * w..(c + 1) * h * w];
                let all: f64 = plane.iter().map(|&v| v as f64).sum();
                let inside: f64 = (p.begin[0]..p.begin[0] + p.len[0]).map(|y| plane[y * w + p.begin[1]..y * w + p.begin[1] + p.len[1]].iter().map(|&v| v as f64).sum::<f64>()).sum();
                self.samples[k].frame[c].push(all / (h * w) as f64);
                self.samples[k].roi[c].push(inside / (p.len[0] * p.len[1]) as f64);
            }
        }
    }

    /// Replaces frame `f`'s ROI means of every pool reading `value` with those of `data`, the
    /// value as the cropped model computes it ([1, C, h, w]).
    pub fn take_means(&mut self, value: &str, f: usize, data: &[f32]) {
        for k in (0..self.nodes.len()).filter(|&k| self.nodes[k].1 == value) {
            let s = &mut self.samples[k];
            if s.channels == 0 || !data.len().is_multiple_of(s.channels) || s.roi[0].len() <= f {
                continue;
            }
            let plane = data.len() / s.channels;
            for c in 0..s.channels {
                s.roi[c][f] = data[c * plane..(c + 1) * plane].iter().map(|&v| v as f64).sum::<f64>() / plane as f64;
            }
        }
    }

    /// Fits pool `k`'s correction and writes it into `g` after the pool: every reader of the
    /// pooled means reads the corrected ones. Nodes are only appended; the caller sorts.
    pub fn emit(&self, g: &mut GraphProto, k: usize, mode: Mode) -> Option<PoolReport> {
        let s = &self.samples[k];
        // A bound on the mix as on the halos' (untrusted channel counts): past it, no correction.
        if mode == Mode::Zero || s.roi.first().map_or(0, Vec::len) < FOLDS || s.channels * s.channels > super::halo::MAX_MIX {
            return None;
        }
        let (lambda, rel_error) = choose(s, mode);
        let (w, b) = solve(&moments(s, 0..s.roi[0].len()), lambda);
        let out = g.node[self.nodes[k].0].output[0].clone();
        let c = s.channels;
        let mix = constant(g, &format!("{out}_frame_mix"), vec![c, c, 1, 1], w.iter().map(|&v| v as f32).collect());
        let offset = constant(g, &format!("{out}_frame_offset"), vec![c], b.iter().map(|&v| v as f32).collect());
        let corrected = node(g, "Conv", &format!("{out}_frame"), vec![out.clone(), mix, offset], vec![attr::make_ints("kernel_shape", vec![1, 1])]);
        // Every reader of the pooled means but the correction itself (the last node) reads it.
        let last = g.node.len() - 1;
        for n in &mut g.node[..last] {
            n.input.iter_mut().filter(|v| **v == out).for_each(|v| *v = corrected.clone());
        }
        for o in g.output.iter_mut().filter(|o| o.name == out) {
            o.name = corrected.clone();
        }
        Some(PoolReport { value: self.nodes[k].1.clone(), channels: c, lambda, rel_error })
    }
}

/// The moments of frames `range` of one pool.
fn moments(s: &Samples, range: std::ops::Range<usize>) -> Moments {
    let mut m = Moments::new(s.channels, s.channels);
    let cols = |v: &Vec<Vec<f64>>| v.iter().map(|c| c[range.clone()].to_vec()).collect::<Vec<_>>();
    m.add_columns(&cols(&s.roi), &cols(&s.frame));
    m
}

fn identity(c: usize) -> Vec<f64> {
    (0..c * c).map(|k| if k / c == k % c { 1.0 } else { 0.0 }).collect()
}

/// (W, b) with ridge `lambda` towards the identity, or the intercept alone for None.
fn solve(m: &Moments, lambda: Option<f64>) -> (Vec<f64>, Vec<f64>) {
    let eye = identity(m.d);
    lambda.and_then(|l| m.solve(l, Some(&eye))).unwrap_or_else(|| m.intercept_only(&eye))
}

/// The pull with the least held-out error over the folds (`Mean`: the intercept alone), and
/// that error relative to the uncorrected crop's (W = I, b = 0).
fn choose(s: &Samples, mode: Mode) -> (Option<f64>, f64) {
    let n = s.roi[0].len();
    let folds: Vec<Moments> = (0..FOLDS).map(|f| moments(s, f * n / FOLDS..(f + 1) * n / FOLDS)).collect();
    let held_out = |lambda: Option<f64>| -> f64 {
        (0..FOLDS)
            .map(|f| {
                let mut train = Moments::new(s.channels, s.channels);
                folds.iter().enumerate().filter(|(j, _)| *j != f).for_each(|(_, m)| train.merge(m));
                let (w, b) = solve(&train, lambda);
                folds[f].residual(&w, &b)
            })
            .sum()
    };
    let none: f64 = folds.iter().map(|m| m.residual(&identity(s.channels), &vec![0.0; s.channels])).sum();
    let mut candidates = vec![None];
    if mode == Mode::Linear {
        candidates.extend(LAMBDAS.iter().map(|&l| Some(l)));
    }
    let (best, err) = candidates.into_iter().map(|l| (l, held_out(l))).fold((None, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
    (best, err / none.max(1e-300))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Frame means that are an exact affine map of the ROI's are found (the least pull wins and
    /// the held-out error vanishes); the intercept alone cannot.
    #[test]
    fn an_exact_affine_relation_is_recovered() {
        let (c, n) = (3usize, 64usize);
        let mut rng = crate::optics::rng::Rng::new(3);
        let w = [[0.6, 0.2, 0.0], [0.0, 0.9, -0.3], [0.1, 0.0, 0.7]];
        let mut s = Samples { channels: c, roi: vec![Vec::new(); c], frame: vec![Vec::new(); c] };
        for _ in 0..n {
            let x: Vec<f64> = (0..c).map(|_| rng.normal()).collect();
            for i in 0..c {
                s.roi[i].push(x[i]);
                s.frame[i].push(0.5 + (0..c).map(|j| w[i][j] * x[j]).sum::<f64>());
            }
        }
        let (lambda, err) = choose(&s, Mode::Linear);
        assert_eq!(lambda, Some(LAMBDAS[0]));
        assert!(err < 1e-3, "held-out error {err}");
        let (fit, b) = solve(&moments(&s, 0..n), Some(1e-6));
        for i in 0..c {
            for j in 0..c {
                assert!((fit[i * c + j] - w[i][j]).abs() < 1e-3);
            }
            assert!((b[i] - 0.5).abs() < 1e-3);
        }
        let (_, mean_err) = choose(&s, Mode::Mean);
        assert!(mean_err > 0.1, "the intercept alone reached {mean_err}");
    }
}
