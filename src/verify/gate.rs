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
//! Every threshold is optional; an absent one is not checked.

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
}

impl Gate {
    pub fn load(path: &Path) -> Result<Gate> {
        load_gate_file(path)
    }
}

/// A gate file of any kind (verify's, stress's), with the messages both give.
pub fn load_gate_file<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read gate file {}", path.display()))?;
    yaml_serde::from_str(&text).map_err(|e| anyhow!("gate file {}: {e}", path.display()))
}

#[derive(Debug, Clone, Serialize)]
pub struct Check {
    pub name: String,
    pub value: f64,
    pub threshold: f64,
    /// "max" (value must not exceed) or "min" (value must reach).
    pub kind: &'static str,
    pub passed: bool,
}

impl Check {
    pub fn max(name: impl Into<String>, value: f64, threshold: f64) -> Check {
        Check { name: name.into(), value, threshold, kind: "max", passed: value <= threshold }
    }
    pub fn min(name: impl Into<String>, value: f64, threshold: f64) -> Check {
        Check { name: name.into(), value, threshold, kind: "min", passed: value >= threshold }
    }
}
