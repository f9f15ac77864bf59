//! Stress gate files: thresholds every candidate must meet under every condition (or the
//! conditions named), for CI.
//!
//! ```yaml
//! min_agreement: 0.5        # mAP@.5:.95 against the reference's detections on the stressed frames
//! max_rel_l2: 0.5           # worst output group (boxes, objectness, classes)
//! max_extra_nonfinite: 0    # NaN/Inf outputs where the reference's are finite
//! max_saturation: 0.02      # INT8: the worst layer's share of values beyond its calibrated range
//! max_fp16_headroom: 0.5    # FP16: the worst layer's max |a| / 65504
//! conditions: [clean, noise_q200, gain_x2]   # optional: gate only these
//! ```

use super::ConditionReport;
use crate::verify::gate::Check;
use anyhow::{bail, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, Default, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct StressGate {
    pub min_agreement: Option<f64>,
    pub max_rel_l2: Option<f64>,
    pub max_extra_nonfinite: Option<usize>,
    pub max_saturation: Option<f64>,
    pub max_fp16_headroom: Option<f64>,
    pub conditions: Option<Vec<String>>,
}

impl StressGate {
    pub fn load(path: &Path) -> Result<StressGate> {
        crate::verify::gate::load_gate_file(path)
    }

    /// Every threshold against every gated condition and candidate. A condition named in the
    /// gate but not run is an error: a typo must not pass silently.
    pub fn checks(&self, reports: &[ConditionReport]) -> Vec<Check> {
        let mut out = Vec::new();
        for r in reports.iter().filter(|r| self.conditions.as_ref().is_none_or(|c| c.contains(&r.name))) {
            for (cand, o) in &r.candidates {
                let name = |what: &str| format!("{} / {cand}: {what}", r.name);
                if let (Some(t), Some(a)) = (self.min_agreement, o.agreement) {
                    out.push(Check::min(name("mAP@.5:.95 agreement"), a, t));
                }
                if let Some(t) = self.max_rel_l2 {
                    out.push(Check::max(name("worst group rel L2"), o.worst_rel_l2, t));
                }
                if let Some(t) = self.max_extra_nonfinite {
                    out.push(Check::max(name("non-finite outputs beyond the reference's"), o.extra_nonfinite as f64, t as f64));
                }
                match (o.layers.as_ref().map(|l| l.measure), o.layers.as_ref().map(|l| l.worst)) {
                    (Some("saturation"), Some(v)) if self.max_saturation.is_some() => out.push(Check::max(name("worst layer saturation"), v, self.max_saturation.unwrap_or_default())),
                    (Some("fp16_headroom"), Some(v)) if self.max_fp16_headroom.is_some() => out.push(Check::max(name("worst layer f16 headroom"), v, self.max_fp16_headroom.unwrap_or_default())),
                    _ => {}
                }
            }
        }
        out
    }

    /// Refuses a gate naming a condition the run does not have.
    pub fn validate(&self, run: &[String]) -> Result<()> {
        for c in self.conditions.iter().flatten() {
            if !run.contains(c) {
                bail!("the gate names condition '{c}', which this run does not have (it runs: {})", run.join(", "));
            }
        }
        Ok(())
    }
}
