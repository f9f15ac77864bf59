//! How much each class of channels is worth.
//!
//! Every weight tensor that touches a class contributes: a convolution's filter producing
//! the channel and the slices of later convolutions reading it. Each tensor's scores are
//! divided by their mean over its channels before they are summed, so a 3x3 conv with large
//! weights does not drown a 1x1 conv reading the same channels (Torch-Pruning's "mean"
//! normalizer does the same).

use crate::analysis::channels::ChannelAnalysis;
use crate::ir::Graph;
use crate::onnx::attr;
use crate::onnx::tensor_proto::to_tensor;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Criterion {
    L1,
    L2,
    /// |gamma| of the BatchNorms in the group; groups without one fall back to L1.
    BnGamma,
    /// Mean |activation| on calibration frames, over every value of the group.
    Activation,
}

/// Per-class scores accumulated from normalized per-channel contributions.
struct Scores<'a> {
    a: &'a ChannelAnalysis,
    total: Vec<f64>,
}

impl Scores<'_> {
    /// Adds `per_channel` (one score per channel of `value`), normalized by its mean.
    fn add(&mut self, value: &str, per_channel: &[f64]) {
        let Some(classes) = self.a.classes_of(value) else { return };
        if classes.len() != per_channel.len() {
            return;
        }
        let mean = per_channel.iter().sum::<f64>() / per_channel.len().max(1) as f64;
        if !(mean > 0.0 && mean.is_finite()) {
            return;
        }
        for (c, s) in classes.iter().zip(per_channel) {
            self.total[*c] += s / mean;
        }
    }
}

fn norm(v: impl Iterator<Item = f32>, l2: bool) -> f64 {
    if l2 {
        v.map(|x| (x as f64).powi(2)).sum::<f64>().sqrt()
    } else {
        v.map(|x| (x as f64).abs()).sum()
    }
}

/// L1 / L2 filter norms of every convolution, summed per class.
pub fn magnitude(g: &Graph, a: &ChannelAnalysis, l2: bool) -> Vec<f64> {
    let mut s = Scores { a, total: vec![0.0; a.class_slots.len()] };
    for &i in &g.order {
        let n = g.node(i);
        if !matches!(n.op_type.as_str(), "Conv" | "ConvTranspose") {
            continue;
        }
        let Some(w) = n.input.get(1).and_then(|w| g.initializers.get(w.as_str())).and_then(|t| to_tensor(t).ok()) else { continue };
        let Some(wv) = w.as_f32() else { continue };
        if w.shape.len() < 3 {
            continue;
        }
        let group = attr::int(n, "group", 1).max(1) as usize;
        let (d0, d1) = (w.shape[0], w.shape[1]);
        let taps: usize = w.shape[2..].iter().product();
        let at = |r: usize, c: usize| &wv[(r * d1 + c) * taps..(r * d1 + c + 1) * taps];
        // Rows: Conv output channels / ConvTranspose input channels.
        let rows: Vec<f64> = (0..d0).map(|r| norm((0..d1).flat_map(|c| at(r, c).iter().copied()), l2)).collect();
        // Columns, per segment: channel (seg * d1 + c) reads/writes rows of its segment only.
        let seg_rows = d0 / group;
        let cols: Vec<f64> = (0..group * d1).map(|k| norm((0..seg_rows).flat_map(|r| at((k / d1) * seg_rows + r, k % d1).iter().copied()), l2)).collect();
        let (row_value, col_value) = if n.op_type == "Conv" { (&n.output[0], &n.input[0]) } else { (&n.input[0], &n.output[0]) };
        s.add(row_value, &rows);
        if group == 1 || d1 > 1 {
            s.add(col_value, &cols);
        }
    }
    s.total
}

/// |gamma| of each BatchNormalization; classes no BN touches get their L1 score instead.
pub fn bn_gamma(g: &Graph, a: &ChannelAnalysis) -> (Vec<f64>, usize) {
    let mut s = Scores { a, total: vec![0.0; a.class_slots.len()] };
    let mut seen = vec![false; a.class_slots.len()];
    for &i in &g.order {
        let n = g.node(i);
        if n.op_type != "BatchNormalization" {
            continue;
        }
        let Some(gamma) = n.input.get(1).and_then(|w| g.initializers.get(w.as_str())).and_then(|t| to_tensor(t).ok()) else { continue };
        let Some(v) = gamma.as_f32() else { continue };
        let abs: Vec<f64> = v.iter().map(|x| x.abs() as f64).collect();
        s.add(&n.output[0], &abs);
        for c in a.classes_of(&n.output[0]).unwrap_or_default() {
            seen[c] = true;
        }
    }
    let l1 = magnitude(g, a, false);
    let fallback = seen.iter().filter(|s| !**s).count();
    (s.total.iter().zip(&seen).zip(&l1).map(|((&t, &k), &l)| if k { t } else { l }).collect(), fallback)
}

/// Mean |activation| per channel of every analysed value (from calibration runs).
pub fn activation(a: &ChannelAnalysis, mean_abs: &HashMap<String, Vec<f64>>) -> Vec<f64> {
    let mut s = Scores { a, total: vec![0.0; a.class_slots.len()] };
    for (v, m) in mean_abs {
        s.add(v, m);
    }
    s.total
}
