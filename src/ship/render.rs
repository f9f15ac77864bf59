//! The one screen of `ship`: a table of the variants, then where the artifacts are.

use super::{ShipReport, Variant};
use std::fmt::Write;

impl ShipReport {
    pub fn render(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "pdi-compile ship  {}  ->  {}", self.model, self.out);
        let _ = writeln!(s, "checked on {}; timed on {} threads (ORT and tract alike), median of {} runs, one interleaved loop", self.frames, self.threads, self.runs);
        let _ = writeln!(s, "mAP is mAP@0.5:0.95; agreement scores each variant's detections against the original's\n");
        let labels = self.variants.iter().any(|v| v.map_labels.is_some());
        let _ = writeln!(
            s,
            "{:<12} {:>10} {:>9} {:>9} {:>16} {:>17} {:>11} {:>19}",
            "variant",
            "size",
            "MACs",
            "params",
            "ORT ms (x orig)",
            "tract ms (x orig)",
            if labels { "mAP labels" } else { "" },
            "agreement ort/tract"
        );
        let original = self.variants.first().and_then(|v| v.ort_ms).unwrap_or(f64::NAN);
        for v in &self.variants {
            let _ = writeln!(
                s,
                "{:<12} {:>10} {:>9} {:>9} {:>16} {:>17} {:>11} {:>19}",
                v.name,
                human(v.bytes as f64, "B"),
                human(v.macs as f64, ""),
                human(v.params as f64, ""),
                timing(v.ort_ms, original),
                timing(v.tract_ms, original),
                v.map_labels.map_or(String::new(), |m| format!("{m:.4}")),
                agreement(v),
            );
        }
        for f in &self.failed {
            let _ = writeln!(s, "FAILED, no artifact: {f}");
        }
        for v in &self.variants {
            if let Some(n) = &v.note {
                let _ = writeln!(s, "note: {}: {n}", v.name);
            }
        }
        let _ = writeln!(s, "\ndeploy");
        for r in &self.recommended {
            let _ = writeln!(s, "  {:<12} {:<12} {}", r.target, r.variant.as_deref().unwrap_or("-"), r.why);
        }
        let _ = writeln!(s, "\nartifacts");
        for v in self.variants.iter().skip(1) {
            let _ = writeln!(s, "  {:<12} {}/  {}", v.name, v.folder, v.file);
        }
        let _ = writeln!(s, "  {:<12} {}/  model.onnx, rknn.yaml, dataset.txt, calib/ (the toolkit's input)", "rknn", self.rknn);
        // The notes above already said the warnings that are variants' notes.
        let unsaid: Vec<&String> = self.warnings.iter().filter(|w| !self.variants.iter().any(|v| v.note.as_ref().is_some_and(|n| w.ends_with(n.as_str())))).collect();
        if let Some(first) = unsaid.first() {
            let _ = writeln!(s, "{} more warning(s), listed in ship.json; the first: {first}", unsaid.len());
        }
        let _ = writeln!(s, "full report: {}/ship.json (and report.json in each folder); {:.0} s in all", self.out, self.seconds);
        s
    }
}

fn timing(ms: Option<f64>, original: f64) -> String {
    ms.map_or_else(|| "-".into(), |ms| format!("{ms:.2} ({:.2})", ms / original))
}

fn agreement(v: &Variant) -> String {
    match (v.agreement, v.agreement_tract) {
        (Some(a), Some(t)) => format!("{a:.3} / {t:.3}"),
        (Some(a), None) => format!("{a:.3}"),
        _ => "-".into(),
    }
}

/// 4.30 MB, 1.23 G, 612 k: three significant digits are what a table reader compares.
fn human(x: f64, unit: &str) -> String {
    let (v, p) = match x {
        x if x >= 1e9 => (x / 1e9, "G"),
        x if x >= 1e6 => (x / 1e6, "M"),
        x if x >= 1e3 => (x / 1e3, "k"),
        x => (x, ""),
    };
    format!("{v:.2} {p}{unit}").trim_end().to_string()
}
