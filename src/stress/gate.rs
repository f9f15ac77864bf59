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
    /// Keys whose check may go unmeasured (`--allow-unmeasured`), not from the file.
    #[serde(skip)]
    pub allow_unmeasured: Vec<String>,
}

/// The keys of a stress gate file that are thresholds.
pub const KEYS: &[&str] = &["min_agreement", "max_rel_l2", "max_extra_nonfinite", "max_saturation", "max_fp16_headroom"];

impl StressGate {
    /// The gate file, with the keys `allow` lets go unmeasured (refused when not gate keys).
    pub fn load(path: &Path, allow: Vec<String>) -> Result<StressGate> {
        let g: StressGate = crate::verify::gate::load_gate_file(path)?;
        crate::verify::gate::allow_unmeasured(&mut [], &allow, KEYS)?;
        Ok(StressGate { allow_unmeasured: allow, ..g })
    }

    /// Every threshold against every gated condition and candidate. A condition named in the
    /// gate but not run is an error: a typo must not pass silently. A layer measure applies to
    /// the candidates of its kind (saturation to INT8, headroom to FP16); a threshold no
    /// candidate of the run could be measured by is reported as not measured.
    pub fn checks(&self, reports: &[ConditionReport]) -> Vec<Check> {
        let mut out = Vec::new();
        let gated: Vec<&ConditionReport> = reports.iter().filter(|r| self.conditions.as_ref().is_none_or(|c| c.contains(&r.name))).collect();
        let mut measured = [false; 2]; // saturation, headroom
        for r in &gated {
            for (cand, o) in &r.candidates {
                let name = |what: &str| format!("{} / {cand}: {what}", r.name);
                match (self.min_agreement, o.agreement) {
                    (Some(t), Some(a)) => out.push(Check::min("min_agreement", name("mAP@.5:.95 agreement"), a, t)),
                    (Some(t), None) => out.push(Check::unmeasured("min_agreement", name("mAP@.5:.95 agreement"), "min", t, "the reference has no decoded detection output to score")),
                    _ => {}
                }
                if let Some(t) = self.max_rel_l2 {
                    out.push(Check::max("max_rel_l2", name("worst group rel L2"), o.worst_rel_l2, t));
                }
                if let Some(t) = self.max_extra_nonfinite {
                    out.push(Check::max("max_extra_nonfinite", name("non-finite outputs beyond the reference's"), o.extra_nonfinite as f64, t as f64));
                }
                match (o.layers.as_ref().map(|l| l.measure), o.layers.as_ref().map(|l| l.worst)) {
                    (Some("saturation"), Some(v)) if self.max_saturation.is_some() => {
                        measured[0] = true;
                        out.push(Check::max("max_saturation", name("worst layer saturation"), v, self.max_saturation.unwrap_or_default()))
                    }
                    (Some("fp16_headroom"), Some(v)) if self.max_fp16_headroom.is_some() => {
                        measured[1] = true;
                        out.push(Check::max("max_fp16_headroom", name("worst layer f16 headroom"), v, self.max_fp16_headroom.unwrap_or_default()))
                    }
                    _ => {}
                }
            }
        }
        if let (Some(t), false) = (self.max_saturation, measured[0]) {
            out.push(Check::unmeasured("max_saturation", "worst layer saturation", "max", t, "no candidate of this run is INT8"));
        }
        if let (Some(t), false) = (self.max_fp16_headroom, measured[1]) {
            out.push(Check::unmeasured("max_fp16_headroom", "worst layer f16 headroom", "max", t, "no candidate of this run is FP16"));
        }
        // Unknown keys were refused at load.
        let _ = crate::verify::gate::allow_unmeasured(&mut out, &self.allow_unmeasured, KEYS);
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
