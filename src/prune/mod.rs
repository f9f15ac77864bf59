//! Structured channel pruning on the ONNX graph: which channels go ([`select`]), how much
//! each is worth ([`importance`]), rewriting the weights ([`apply`]), and recovering the
//! accuracy without training ([`compensate`]).

pub mod apply;
pub mod compensate;
pub mod importance;
pub mod sensitivity;

use crate::analysis::channels::ChannelAnalysis;
use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Scope {
    /// The same ratio in every group.
    Uniform,
    /// One threshold on group-normalized importance across the whole model.
    Global,
}

pub struct SelectOptions {
    pub ratio: f64,
    pub round_to: usize,
    pub scope: Scope,
    /// Per-group ratios by group anchor (sensitivity allocation); groups not named keep
    /// every channel. Overrides `ratio` and `scope`.
    pub per_group: Option<std::collections::HashMap<String, f64>>,
}

/// What happened to one group.
#[derive(Serialize, Clone, Debug)]
pub struct GroupPlan {
    pub anchor: String,
    pub before: usize,
    pub after: usize,
    /// Why it kept every channel, or how its count was rounded.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub note: Option<String>,
}

pub struct Plan {
    /// Per class: kept or removed.
    pub keep: Vec<bool>,
    pub groups: Vec<GroupPlan>,
}

/// How many of `n` channels to keep for a wanted `target`: a multiple of `round_to` (NPU
/// lanes) when the group is big enough for that to still prune; small groups (toy widths)
/// round to the nearest integer instead, and say so. With segments, a multiple of them.
fn keep_count(n: usize, target: f64, round_to: usize, segments: usize) -> (usize, Option<String>) {
    let seg = segments.max(1);
    let step = if round_to > 1 && n >= 2 * round_to { lcm(round_to, seg) } else { seg };
    let mut keep = ((target / step as f64).round() as usize).max(1) * step;
    keep = keep.min(n);
    let note = (round_to > 1 && n < 2 * round_to).then(|| format!("{n} channels: too few to keep a multiple of {round_to}, rounded to {step}"));
    if !keep.is_multiple_of(seg) {
        keep = n;
    }
    (keep, note)
}

fn lcm(a: usize, b: usize) -> usize {
    fn gcd(a: usize, b: usize) -> usize {
        if b == 0 { a } else { gcd(b, a % b) }
    }
    a / gcd(a, b) * b
}

/// Chooses the channels to keep. `importance` is per class; higher is kept first.
pub fn select(a: &ChannelAnalysis, importance: &[f64], opts: &SelectOptions) -> Plan {
    let mut keep = vec![true; a.class_slots.len()];
    // Global scope: per-group normalized scores, one threshold at the ratio's quantile.
    let normalized: Vec<f64> = {
        let mut v = importance.to_vec();
        for g in &a.groups {
            let mean = g.classes.iter().map(|&c| importance[c]).sum::<f64>() / g.classes.len().max(1) as f64;
            for &c in &g.classes {
                v[c] = if mean > 0.0 { importance[c] / mean } else { 1.0 };
            }
        }
        v
    };
    let threshold = {
        let mut all: Vec<f64> = a.groups.iter().filter(|g| g.frozen.is_none()).flat_map(|g| g.classes.iter().map(|&c| normalized[c])).collect();
        all.sort_by(f64::total_cmp);
        all.get(((all.len() as f64) * opts.ratio) as usize).copied().unwrap_or(f64::INFINITY)
    };
    let mut groups = Vec::new();
    for g in &a.groups {
        let n = g.classes.len();
        let mut plan = GroupPlan { anchor: g.anchor.clone(), before: n, after: n, note: None };
        if let Some(why) = &g.frozen {
            plan.note = Some(format!("kept: {why}"));
            groups.push(plan);
            continue;
        }
        let target = match (&opts.per_group, opts.scope) {
            (Some(ratios), _) => n as f64 * (1.0 - ratios.get(&g.anchor).copied().unwrap_or(0.0)),
            (None, Scope::Uniform) => n as f64 * (1.0 - opts.ratio),
            (None, Scope::Global) => g.classes.iter().filter(|&&c| normalized[c] >= threshold).count() as f64,
        };
        let parts = g.segments.first().map_or(1, |s| s.1);
        let (k, note) = keep_count(n, target, opts.round_to, parts);
        plan.note = note;
        if k >= n {
            groups.push(plan);
            continue;
        }
        let chosen = match g.segments.first() {
            None => top(&g.classes, importance, k),
            Some((v, parts)) => {
                let order = a.classes_of(v).expect("segment values are analysed");
                let per = order.len() / parts;
                order.chunks(per).flat_map(|seg| top(seg, importance, k / parts)).collect()
            }
        };
        let balanced = g.segments.iter().all(|(v, parts)| {
            let order = a.classes_of(v).expect("segment values are analysed");
            let per = order.len() / parts;
            let counts: Vec<usize> = order.chunks(per).map(|seg| seg.iter().filter(|c| chosen.contains(c)).count()).collect();
            counts.iter().all(|&x| x == counts[0])
        });
        if !balanced {
            plan.note = Some("kept: grouped convolutions disagree on segments".into());
            groups.push(plan);
            continue;
        }
        for &c in &g.classes {
            keep[c] = chosen.contains(&c);
        }
        plan.after = k;
        groups.push(plan);
    }
    Plan { keep, groups }
}

/// The `k` classes of `classes` with the highest importance (earlier first on ties).
fn top(classes: &[usize], importance: &[f64], k: usize) -> Vec<usize> {
    let mut order: Vec<usize> = classes.to_vec();
    order.sort_by(|&x, &y| importance[y].total_cmp(&importance[x]));
    order.truncate(k);
    order
}

#[cfg(test)]
mod tests {
    use super::keep_count;

    #[test]
    fn counts_round_to_lanes_when_they_can() {
        assert_eq!(keep_count(256, 128.0, 16, 1).0, 128);
        assert_eq!(keep_count(48, 24.0, 16, 1).0, 32); // 24 -> nearest multiple of 16
        assert_eq!(keep_count(8, 4.0, 8, 1), (4, Some("8 channels: too few to keep a multiple of 8, rounded to 1".into())));
        assert_eq!(keep_count(16, 8.0, 8, 4).0, 8);
        assert_eq!(keep_count(4, 0.2, 8, 1).0, 1);
    }
}
