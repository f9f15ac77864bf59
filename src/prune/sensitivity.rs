//! Sensitivity-guided ratios: how far pruning each dependency group alone moves the detection
//! outputs, and per-group ratios that meet a budget with the least predicted damage.
//!
//! Damage is the worst output group's rel L2 (boxes, objectness, classes judged apart)
//! against the unpruned model on calibration frames, with no compensation (what recovery
//! starts from), or the confident boxes' error as a fraction of their own size where that is
//! larger: a box branch's cut barely moves the boxes' pixel coordinates against their norm,
//! and costs mAP at high IoU all the same. The allocation is greedy on damage per MAC saved,
//! one level of one group at a time (squared damage per MAC saved), and checks the budget on
//! the real pruned model after every step (MAC savings of neighbouring groups do not add up:
//! a convolution between two pruned groups loses both).

use serde::Serialize;
use std::collections::HashMap;

/// Ratios each group is measured at. Rounding to lanes can merge levels; duplicates are
/// measured once.
pub const LEVELS: &[f64] = &[0.25, 0.5, 0.75];

#[derive(Serialize, Clone, Debug)]
pub struct Level {
    pub ratio: f64,
    /// Channels kept at this ratio (after rounding).
    pub keep: usize,
    /// Worst output group's rel L2, or the confident boxes' error at their scale where larger,
    /// with only this group pruned.
    pub damage: f64,
    /// MACs this group's pruning alone removes.
    pub macs_saved: u64,
}

#[derive(Serialize, Clone, Debug)]
pub struct GroupSensitivity {
    pub anchor: String,
    pub channels: usize,
    pub levels: Vec<Level>,
    /// The ratio the allocation chose (0: untouched).
    pub chosen: f64,
}

/// What the budget is measured in.
pub enum Budget<'a> {
    /// Largest MACs allowed.
    Macs(u64),
    /// A predicate on the ratios: true when they meet the budget (a latency measurement).
    Check(&'a mut dyn FnMut(&HashMap<String, f64>) -> anyhow::Result<bool>),
}

/// Per-group ratios meeting `budget`, cheapest predicted damage per MAC first. `macs_of`
/// gives the real MACs of the model pruned with given ratios. Returns the ratios and
/// whether the budget was met (false when every level of every group is taken).
pub fn allocate(groups: &mut [GroupSensitivity], mut budget: Budget, macs_of: &mut dyn FnMut(&HashMap<String, f64>) -> anyhow::Result<u64>) -> anyhow::Result<(HashMap<String, f64>, bool)> {
    let mut level: Vec<Option<usize>> = vec![None; groups.len()];
    let mut ratios = HashMap::new();
    loop {
        let met = match &mut budget {
            Budget::Macs(limit) => macs_of(&ratios)? <= *limit,
            Budget::Check(check) => check(&ratios)?,
        };
        if met {
            return Ok((ratios, true));
        }
        // Independent perturbations add in energy: the greedy adds squared damage (a group
        // that nearly destroys the outputs alone is never worth its MACs).
        let cost = |g: &GroupSensitivity, l: Option<usize>| l.map_or((0.0, 0), |i| (g.levels[i].damage.powi(2), g.levels[i].macs_saved));
        let next = groups
            .iter()
            .enumerate()
            .filter_map(|(i, g)| {
                let j = level[i].map_or(0, |l| l + 1);
                let lv = g.levels.get(j)?;
                let (d0, s0) = cost(g, level[i]);
                let saved = lv.macs_saved.saturating_sub(s0).max(1) as f64;
                Some((i, j, (lv.damage.powi(2) - d0).max(0.0) / saved))
            })
            .min_by(|a, b| a.2.total_cmp(&b.2));
        let Some((i, j, _)) = next else { return Ok((ratios, false)) };
        level[i] = Some(j);
        groups[i].chosen = groups[i].levels[j].ratio;
        ratios.insert(groups[i].anchor.clone(), groups[i].levels[j].ratio);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn group(anchor: &str, levels: &[(f64, f64, u64)]) -> GroupSensitivity {
        GroupSensitivity { anchor: anchor.into(), channels: 64, levels: levels.iter().map(|&(ratio, damage, macs_saved)| Level { ratio, keep: 0, damage, macs_saved }).collect(), chosen: 0.0 }
    }

    #[test]
    fn cheap_damage_per_mac_goes_first_and_the_budget_is_checked_on_real_macs() {
        // "a" saves a lot at little damage, "b" hurts: "a" is pruned to its last level first.
        let mut groups = vec![group("a", &[(0.25, 0.01, 100), (0.5, 0.02, 200), (0.75, 0.05, 300)]), group("b", &[(0.25, 0.5, 100), (0.5, 0.9, 200)])];
        let total = 1000u64;
        let mut macs = |r: &HashMap<String, f64>| -> anyhow::Result<u64> {
            let saved: f64 = r.values().map(|v| 400.0 * v).sum();
            Ok(total - saved as u64)
        };
        let (ratios, met) = allocate(&mut groups, Budget::Macs(700), &mut macs).unwrap();
        assert!(met);
        assert_eq!(ratios.get("a"), Some(&0.75));
        assert_eq!(ratios.get("b"), None, "the sensitive group stays whole while the cheap one meets the budget");
        assert_eq!(groups[0].chosen, 0.75);
    }

    #[test]
    fn an_unreachable_budget_says_so() {
        let mut groups = vec![group("a", &[(0.5, 0.1, 10)])];
        let mut macs = |r: &HashMap<String, f64>| -> anyhow::Result<u64> { Ok(if r.is_empty() { 100 } else { 90 }) };
        let (ratios, met) = allocate(&mut groups, Budget::Macs(50), &mut macs).unwrap();
        assert!(!met);
        assert_eq!(ratios.get("a"), Some(&0.5));
    }
}
