//! The stress report as DIR/stress.json, DIR/stress.md and a heatmap of agreement
//! (conditions x candidates) as DIR/stress.svg and DIR/stress.png.

use super::{Outcome, StressReport};
use crate::canvas::{self, Shape};
use crate::fsutil::{write_atomic, StagedDir};
use anyhow::Result;
use std::fmt::Write;
use std::path::Path;

/// A candidate "breaks" under a condition when its agreement falls this far below its
/// agreement on clean frames (a few boxes of 32 frames move mAP by ~0.01: noise).
const BREAK_DROP: f64 = 0.05;
const CELL_W: f64 = 150.0;
const CELL_H: f64 = 22.0;
const LEFT: f64 = 210.0;
const TOP: f64 = 70.0;

/// Writes the folder whole (replacing an earlier one), or leaves it as it was.
pub fn write(out: &Path, r: &StressReport) -> Result<()> {
    let staged = StagedDir::new(out)?;
    let dir = staged.path();
    write_atomic(&dir.join("stress.json"), serde_json::to_string_pretty(r)?.as_bytes())?;
    write_atomic(&dir.join("stress.md"), markdown(r).as_bytes())?;
    let (shapes, w, h) = heatmap(r);
    write_atomic(&dir.join("stress.svg"), canvas::svg(&shapes, w, h).as_bytes())?;
    write_atomic(&dir.join("stress.png"), &canvas::png(&shapes, w, h)?)?;
    staged.commit()
}

fn cell(o: &Outcome) -> String {
    let a = o.agreement.map_or(format!("no reference boxes; {} own", o.boxes), |a| format!("{a:.3}"));
    let nan = if o.extra_nonfinite > 0 { format!(", NaN/Inf {}", o.extra_nonfinite) } else { String::new() };
    format!("{a} ({:.2e}{nan})", o.worst_rel_l2)
}

fn clean<'a>(r: &'a StressReport, cand: &str) -> Option<&'a Outcome> {
    r.conditions.iter().find(|c| c.name == "clean").and_then(|c| c.candidates.get(cand))
}

pub fn markdown(r: &StressReport) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "# Stress: {}\n", r.reference);
    let _ = writeln!(s, "{} frames per condition ({}); conditions from {}; {} thread(s), {:.0} s.\n", r.frames, r.frame_source, r.condition_source, r.threads, r.seconds);
    let _ = writeln!(s, "mAP@.5:.95 agreement with the reference's detections on the same stressed frames; in brackets the worst output group's rel L2, and NaN/Inf outputs where the reference's are finite.\n");
    let head: Vec<String> = r.candidates.iter().map(|c| format!("{} ({})", c.label, format!("{:?}", c.precision).to_lowercase())).collect();
    let _ = writeln!(s, "| condition | reference boxes | {} |", head.join(" | "));
    let _ = writeln!(s, "|---|---:|{}", "---|".repeat(head.len()));
    for c in &r.conditions {
        let cells: Vec<String> = r.candidates.iter().map(|k| c.candidates.get(&k.label).map_or_else(|| c.skipped.clone().unwrap_or_default(), cell)).collect();
        let nan = if c.reference_nonfinite > 0 { format!(" (NaN/Inf outputs {})", c.reference_nonfinite) } else { String::new() };
        let _ = writeln!(s, "| {} | {}{nan} | {} |", c.name, c.reference_boxes, cells.join(" | "));
    }
    let _ = writeln!(s, "\nWorst condition per candidate (among those with at least {} reference boxes):\n", super::MIN_REFERENCE_BOXES);
    let _ = writeln!(s, "| candidate | clean | worst condition | agreement |\n|---|---:|---|---:|");
    let f = |v: Option<f64>| v.map_or("-".to_string(), |v| format!("{v:.3}"));
    for m in &r.summary {
        let _ = writeln!(s, "| {} | {} | {} | {} |", m.candidate, f(m.clean), m.worst_condition.as_deref().unwrap_or("-"), f(m.worst_agreement));
    }
    if r.conditions.iter().any(|c| c.candidates.values().any(|o| o.layers.is_some())) {
        let _ = writeln!(s, "\n## Layers\n\nINT8: the worst layer's share of values beyond its calibrated range (they clip). FP16: the worst layer's max |a| / 65504 (1 overflows).\n");
        let layered: Vec<&str> = r.candidates.iter().filter(|k| r.conditions.iter().any(|c| c.candidates.get(&k.label).is_some_and(|o| o.layers.is_some()))).map(|k| k.label.as_str()).collect();
        let _ = writeln!(s, "| condition | {} |", layered.join(" | "));
        let _ = writeln!(s, "|---|{}", "---|".repeat(layered.len()));
        for c in r.conditions.iter().filter(|c| c.skipped.is_none()) {
            let cells: Vec<String> = layered
                .iter()
                .map(|k| match c.candidates.get(*k).and_then(|o| o.layers.as_ref()) {
                    Some(l) => match l.worst_layers.first() {
                        Some(w) if l.measure == "saturation" => format!("{:.3}% `{}`", 100.0 * w.value, w.layer),
                        Some(w) => format!("{:.2e} `{}`", w.value, w.layer),
                        None => "-".into(),
                    },
                    None => "-".into(),
                })
                .collect();
            let _ = writeln!(s, "| {} | {} |", c.name, cells.join(" | "));
        }
    }
    let _ = writeln!(s, "\n## What breaks\n\nA candidate breaks under a condition when its agreement falls more than {BREAK_DROP} below its own on clean frames (conditions with at least {} reference boxes), or when it gives NaN/Inf where the reference does not.\n", super::MIN_REFERENCE_BOXES);
    let broken = breaks(r);
    if broken.is_empty() {
        let _ = writeln!(s, "Nothing: every candidate holds under every condition.");
    }
    for b in broken {
        let _ = writeln!(s, "- {b}");
    }
    if !r.checks.is_empty() {
        let _ = writeln!(s, "\n## Gate: {}\n", if r.passed { "passed" } else { "FAILED" });
        for c in r.checks.iter().filter(|c| !c.passed || c.allowed) {
            let _ = writeln!(s, "- {}", c.line());
        }
        let _ = writeln!(s, "- {} of {} checks passed", r.checks.iter().filter(|c| c.passed).count(), r.checks.len());
    }
    s
}

/// One line per (condition, candidate) that breaks, naming the worst layer where known.
pub fn breaks(r: &StressReport) -> Vec<String> {
    let mut out = Vec::new();
    for c in r.conditions.iter().filter(|c| c.name != "clean") {
        let rankable = c.reference_boxes >= super::MIN_REFERENCE_BOXES;
        for (cand, o) in &c.candidates {
            let base = clean(r, cand).and_then(|b| b.agreement);
            let dropped = rankable && matches!((o.agreement, base), (Some(a), Some(b)) if b - a > BREAK_DROP);
            if !dropped && o.extra_nonfinite == 0 {
                continue;
            }
            let mut line = format!("`{}`: {cand}", c.name);
            if let (Some(a), Some(b)) = (o.agreement, base) {
                let _ = write!(line, " agreement {a:.3} (clean {b:.3})");
            }
            if o.extra_nonfinite > 0 {
                let _ = write!(line, ", {} NaN/Inf outputs the reference does not have", o.extra_nonfinite);
            }
            if let Some(w) = o.layers.as_ref().and_then(|l| l.worst_layers.first().map(|w| (l.measure, w))) {
                let _ = match w.0 {
                    "saturation" => write!(line, "; worst layer `{}` clips {:.2}% of its values", w.1.layer, 100.0 * w.1.value),
                    _ => write!(line, "; worst layer `{}` at {:.2e} of f16's range", w.1.layer, w.1.value),
                };
            }
            out.push(line);
        }
    }
    out
}

/// Red at 0, amber at 0.5, green at 1.
fn color(a: f64) -> [u8; 3] {
    let lerp = |x: [u8; 3], y: [u8; 3], t: f64| -> [u8; 3] { std::array::from_fn(|i| (x[i] as f64 + (y[i] as f64 - x[i] as f64) * t).round() as u8) };
    let (red, amber, green) = ([214, 39, 40], [250, 200, 80], [60, 170, 80]);
    let a = a.clamp(0.0, 1.0);
    if a < 0.5 { lerp(red, amber, a / 0.5) } else { lerp(amber, green, (a - 0.5) / 0.5) }
}

fn heatmap(r: &StressReport) -> (Vec<Shape>, u32, u32) {
    const BLACK: [u8; 3] = [20, 20, 20];
    let (cols, rows) = (r.candidates.len() as f64, r.conditions.len() as f64);
    let (w, h) = ((LEFT + cols * CELL_W + 20.0).max(700.0), TOP + rows * CELL_H + 60.0);
    let mut s = vec![Shape::Text { at: (w / 2.0, 26.0), text: "pdi-compile stress: mAP@.5:.95 agreement with the reference".into(), color: BLACK, scale: 1, centered: true }];
    for (j, k) in r.candidates.iter().enumerate() {
        let x = LEFT + (j as f64 + 0.5) * CELL_W;
        s.push(Shape::Text { at: (x, TOP - 22.0), text: k.label.chars().take(18).collect(), color: BLACK, scale: 1, centered: true });
        s.push(Shape::Text { at: (x, TOP - 8.0), text: format!("{:?}", k.precision).to_lowercase(), color: BLACK, scale: 1, centered: true });
    }
    for (i, c) in r.conditions.iter().enumerate() {
        let y = TOP + i as f64 * CELL_H;
        s.push(Shape::Text { at: (8.0, y + 15.0), text: c.name.chars().take(25).collect(), color: BLACK, scale: 1, centered: false });
        for (j, k) in r.candidates.iter().enumerate() {
            let x = LEFT + j as f64 * CELL_W;
            let (fill, text) = match c.candidates.get(&k.label) {
                Some(o) => match o.agreement {
                    Some(a) => (color(a), format!("{a:.3}{}", if o.extra_nonfinite > 0 { " NaN" } else { "" })),
                    None => ([200, 200, 200], format!("no ref boxes, {}", o.boxes)),
                },
                None => ([230, 230, 230], "skipped".into()),
            };
            s.push(Shape::Fill { at: (x + 1.0, y + 1.0), size: (CELL_W - 2.0, CELL_H - 2.0), color: fill });
            s.push(Shape::Text { at: (x + CELL_W / 2.0, y + 15.0), text, color: BLACK, scale: 1, centered: true });
        }
    }
    s.push(Shape::Text { at: (w / 2.0, h - 20.0), text: "red 0, amber 0.5, green 1; NaN: non-finite outputs the reference does not have".into(), color: BLACK, scale: 1, centered: true });
    (s, w as u32, h as u32)
}
