//! Gate files: thresholds a candidate must meet against its reference (CI's pass/fail).
//!
//! ```yaml
//! max_rel_l2: 1.0e-5        # each compared output, candidate on ORT vs reference on ORT
//! max_rel_l2_tract: 1.0e-4  # candidate on tract vs candidate on ORT
//! min_cosine: 0.99999
//! min_map_agreement: 0.99   # candidate's mAP@.5:.95 against the reference's detections
//! max_map_drop: 0.01        # reference mAP@.5:.95 minus candidate's, against labels
//! max_latency_ratio: 1.05   # candidate / reference median latency on ORT
//! ```
//! Every threshold is optional; an absent one is not checked. A threshold that is present is
//! either measured or reported as *not measured* with the reason; an unmeasured check fails the
//! gate unless the command's `--allow-unmeasured KEY` names it (then it is reported as allowed).

use anyhow::{anyhow, Context, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

#[derive(Debug, Default, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct Gate {
    pub max_rel_l2: Option<f64>,
    pub max_rel_l2_tract: Option<f64>,
    pub min_cosine: Option<f64>,
    pub min_map_agreement: Option<f64>,
    pub max_map_drop: Option<f64>,
    pub max_latency_ratio: Option<f64>,
    /// Keys whose check may go unmeasured (`--allow-unmeasured`), not from the file.
    #[serde(skip)]
    pub allow_unmeasured: Vec<String>,
}

impl Gate {
    /// The gate file, with the keys `allow` lets go unmeasured (refused when not gate keys).
    pub fn load(path: &Path, allow: Vec<String>) -> Result<Gate> {
        let g: Gate = load_gate_file(path)?;
        allow_unmeasured(&mut [], &allow, KEYS)?;
        Ok(Gate { allow_unmeasured: allow, ..g })
    }
}

/// A gate file of any kind (verify's, stress's), with the messages both give.
pub fn load_gate_file<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read gate file {}", path.display()))?;
    yaml_serde::from_str(&text).map_err(|e| anyhow!("gate file {}: {e}", path.display()))
}

#[derive(Debug, Clone, Serialize)]
pub struct Check {
    /// The gate file's key this check comes from (`max_map_drop`).
    pub key: &'static str,
    pub name: String,
    /// What was measured; None when the run could not measure it (`unmeasured` says why).
    pub value: Option<f64>,
    pub threshold: f64,
    /// "max" (value must not exceed) or "min" (value must reach).
    pub kind: &'static str,
    pub passed: bool,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub unmeasured: Option<String>,
    /// An unmeasured check that `--allow-unmeasured` let pass.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub allowed: bool,
}

impl Check {
    pub fn max(key: &'static str, name: impl Into<String>, value: f64, threshold: f64) -> Check {
        // `!(v > t)` would pass NaN; a NaN measurement fails every check.
        Check { key, name: name.into(), value: Some(value), threshold, kind: "max", passed: value <= threshold, unmeasured: None, allowed: false }
    }
    pub fn min(key: &'static str, name: impl Into<String>, value: f64, threshold: f64) -> Check {
        Check { key, name: name.into(), value: Some(value), threshold, kind: "min", passed: value >= threshold, unmeasured: None, allowed: false }
    }
    /// A threshold the run could not measure: it fails until `--allow-unmeasured` names it.
    pub fn unmeasured(key: &'static str, name: impl Into<String>, kind: &'static str, threshold: f64, reason: impl Into<String>) -> Check {
        Check { key, name: name.into(), value: None, threshold, kind, passed: false, unmeasured: Some(reason.into()), allowed: false }
    }

    /// One line for a screen: `[pass] name = value (max threshold)`.
    pub fn line(&self) -> String {
        match (&self.value, &self.unmeasured) {
            (Some(v), _) => format!("[{}] {} = {v:.4e} ({} {:.4e})", if self.passed { "pass" } else { "FAIL" }, self.name, self.kind, self.threshold),
            (None, Some(why)) if self.allowed => format!("[not measured, allowed] {} ({} {:.4e}): {why}; --allow-unmeasured {} lets it pass", self.name, self.kind, self.threshold, self.key),
            (None, why) => format!("[FAIL: not measured] {} ({} {:.4e}): {}; give what it needs or --allow-unmeasured {}", self.name, self.kind, self.threshold, why.as_deref().unwrap_or("no value"), self.key),
        }
    }
}

/// Lets the unmeasured checks whose key `allow` names pass (marked as allowed). A key that is
/// not one of `known` is refused: a typo must not silently allow nothing.
pub fn allow_unmeasured(checks: &mut [Check], allow: &[String], known: &[&str]) -> Result<()> {
    for a in allow {
        if !known.contains(&a.as_str()) {
            anyhow::bail!("--allow-unmeasured {a}: not a gate key (keys: {})", known.join(", "));
        }
    }
    for c in checks.iter_mut().filter(|c| c.value.is_none() && allow.iter().any(|a| a == c.key)) {
        c.allowed = true;
        c.passed = true;
    }
    Ok(())
}

/// The keys of a verify gate file.
pub const KEYS: &[&str] = &["max_rel_l2", "max_rel_l2_tract", "min_cosine", "min_map_agreement", "max_map_drop", "max_latency_ratio"];
