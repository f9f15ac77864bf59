//! The bench plot: latency (log) against rel L2 (log) and against mAP agreement, one panel
//! each, Pareto front in red. Laid out once as shapes in pixels, then written as SVG (text
//! left to the viewer's fonts) and as PNG (text from an 8×8 bitmap font compiled in, so no
//! font files or fontconfig are needed).

use super::Row;
use crate::canvas::{self, Shape};
use anyhow::Result;

const WIDTH: u32 = 1280;
const HEIGHT: u32 = 560;
const PANEL_W: f64 = 540.0;
const PANEL_H: f64 = 380.0;
const TOP: f64 = 70.0;
const LEFTS: [f64; 2] = [90.0, 730.0];
/// Where rel L2 = 0 (the original) is drawn on the log axis.
const REL_L2_FLOOR: f64 = 1e-7;
const RED: [u8; 3] = [214, 39, 40];
const GREY: [u8; 3] = [200, 200, 200];
const BLACK: [u8; 3] = [20, 20, 20];


fn color_of(variant: &str) -> [u8; 3] {
    if variant == "original" {
        BLACK
    } else if variant.ends_with("fp16") {
        [44, 160, 44]
    } else if variant.ends_with("int8") {
        [255, 127, 14]
    } else {
        [31, 119, 180]
    }
}

/// An axis mapping values onto pixels, log10 or linear.
struct Axis {
    lo: f64,
    hi: f64,
    log: bool,
}

impl Axis {
    fn new(values: impl Iterator<Item = f64>, log: bool, pad: f64) -> Axis {
        let (mut lo, mut hi) = values.fold((f64::MAX, f64::MIN), |(a, b), v| (a.min(v), b.max(v)));
        if !(lo <= hi) {
            (lo, hi) = (1.0, 10.0);
        }
        if log {
            let (l, h) = (lo.max(1e-12).log10() - pad, hi.max(1e-12).log10() + pad);
            Axis { lo: l, hi: h.max(l + 0.5), log }
        } else {
            let span = (hi - lo).max(1e-3);
            Axis { lo: lo - span * pad, hi: hi + span * pad, log }
        }
    }
    fn unit(&self, v: f64) -> f64 {
        let v = if self.log { v.max(1e-12).log10() } else { v };
        ((v - self.lo) / (self.hi - self.lo)).clamp(0.0, 1.0)
    }
    /// Tick values: 1-2-5 steps on log axes, ~6 even steps on linear ones.
    fn ticks(&self) -> Vec<f64> {
        if self.log {
            // 1-2-5 steps over a few decades; decades alone beyond that, or labels collide.
            let steps: &[f64] = if self.hi - self.lo <= 3.0 { &[1.0, 2.0, 5.0] } else { &[1.0] };
            (self.lo.floor() as i32..=self.hi.ceil() as i32)
                .flat_map(|e| steps.iter().map(move |m| m * 10f64.powi(e)))
                .filter(|v| (self.lo..=self.hi).contains(&v.log10()))
                .collect()
        } else {
            let raw = (self.hi - self.lo) / 6.0;
            let step = [1.0, 2.0, 5.0].iter().map(|m| m * 10f64.powf(raw.log10().floor())).find(|s| *s >= raw).unwrap_or(raw);
            let first = (self.lo / step).ceil() as i64;
            (first..).map(|k| k as f64 * step).take_while(|v| *v <= self.hi).collect()
        }
    }
}

fn label(v: f64) -> String {
    if v == 0.0 {
        "0".into()
    } else if (1e-2..1e4).contains(&v.abs()) {
        format!("{}", (v * 1000.0).round() / 1000.0)
    } else {
        format!("{v:.0e}")
    }
}

/// Height of a label line (8-pixel glyphs and a little air).
const LABEL_H: f64 = 11.0;
/// Line offsets a label tries, nearest its point first.
const LABEL_SHIFTS: [f64; 9] = [0.0, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0];

/// A label's box; `y` is its text baseline (glyphs sit above it).
struct Rect {
    x: f64,
    y: f64,
    w: f64,
    h: f64,
}

impl Rect {
    fn overlaps(&self, o: &Rect) -> bool {
        self.x < o.x + o.w && o.x < self.x + self.w && self.y - self.h < o.y && o.y - o.h < self.y
    }
}

fn layout(rows: &[Row], title: &str) -> Vec<Shape> {
    let mut s = vec![Shape::Text { at: (WIDTH as f64 / 2.0, 28.0), text: format!("pdi-compile bench: {title}"), color: BLACK, scale: 2, centered: true }];
    let x = Axis::new(rows.iter().map(|r| r.latency_ms), true, 0.08);
    let y_rel = Axis::new(rows.iter().map(|r| r.rel_l2.max(REL_L2_FLOOR)), true, 0.2);
    let y_map = Axis::new(rows.iter().filter_map(|r| r.map_agreement), false, 0.08);
    type Pick = fn(&Row) -> Option<(f64, bool)>;
    let panels: [(&Axis, &str, Pick); 2] = [
        (&y_rel, "rel L2 vs original (log)", |r| Some((r.rel_l2.max(REL_L2_FLOOR), r.pareto_rel_l2))),
        (&y_map, "mAP@.5:.95 agreement with original", |r| r.map_agreement.map(|m| (m, r.pareto_map))),
    ];
    for (left, (y, name, pick)) in LEFTS.into_iter().zip(panels) {
        let px = |v: f64| left + x.unit(v) * PANEL_W;
        let py = |v: f64| TOP + (1.0 - y.unit(v)) * PANEL_H;
        for t in x.ticks() {
            s.push(Shape::Line { from: (px(t), TOP), to: (px(t), TOP + PANEL_H), color: GREY, width: 1.0 });
            s.push(Shape::Text { at: (px(t), TOP + PANEL_H + 18.0), text: label(t), color: BLACK, scale: 1, centered: true });
        }
        for t in y.ticks() {
            s.push(Shape::Line { from: (left, py(t)), to: (left + PANEL_W, py(t)), color: GREY, width: 1.0 });
            s.push(Shape::Text { at: (left - 8.0 * label(t).len() as f64 - 6.0, py(t) + 4.0), text: label(t), color: BLACK, scale: 1, centered: false });
        }
        for (a, b) in [((0.0, 0.0), (PANEL_W, 0.0)), ((0.0, PANEL_H), (PANEL_W, PANEL_H)), ((0.0, 0.0), (0.0, PANEL_H)), ((PANEL_W, 0.0), (PANEL_W, PANEL_H))] {
            s.push(Shape::Line { from: (left + a.0, TOP + a.1), to: (left + b.0, TOP + b.1), color: BLACK, width: 1.0 });
        }
        s.push(Shape::Text { at: (left + PANEL_W / 2.0, TOP - 12.0), text: name.into(), color: BLACK, scale: 1, centered: true });
        s.push(Shape::Text { at: (left + PANEL_W / 2.0, TOP + PANEL_H + 40.0), text: "latency, ms (log)".into(), color: BLACK, scale: 1, centered: true });
        let mut front: Vec<(f64, f64)> = rows.iter().filter_map(|r| pick(r).filter(|p| p.1).map(|p| (px(r.latency_ms), py(p.0)))).collect();
        front.sort_by(|a, b| a.0.total_cmp(&b.0));
        for w in front.windows(2) {
            // A step: the front holds its error until the next faster-or-better point.
            s.push(Shape::Line { from: w[0], to: (w[1].0, w[0].1), color: RED, width: 2.0 });
            s.push(Shape::Line { from: (w[1].0, w[0].1), to: w[1], color: RED, width: 2.0 });
        }
        // Labels avoid the markers (Pareto rings included) and each other.
        let mut placed: Vec<Rect> = rows.iter().filter_map(|r| pick(r).map(|(v, _)| (px(r.latency_ms), py(v)))).map(|(x, y)| Rect { x: x - 9.0, y: y + 9.0, w: 18.0, h: 18.0 }).collect();
        for r in rows {
            let Some((v, pareto)) = pick(r) else { continue };
            let at = (px(r.latency_ms), py(v));
            if pareto {
                s.push(Shape::Marker { at, radius: 9.0, color: RED, square: false, filled: false });
            }
            s.push(Shape::Marker { at, radius: 5.0, color: color_of(&r.variant), square: r.engine == "tract", filled: !r.variant.starts_with("pruned") });
            let text = format!("{}/{}", r.variant, r.engine);
            // Labels go right of their point unless that runs past the panel, and move down
            // or up a line at a time off what is already drawn (points often cluster).
            let width = 8.0 * text.len() as f64;
            let x = if at.0 + 9.0 + width > left + PANEL_W { at.0 - 9.0 - width } else { at.0 + 9.0 };
            let free = |y: f64| !placed.iter().any(|p| p.overlaps(&Rect { x, y, w: width, h: LABEL_H }));
            let y = LABEL_SHIFTS.iter().map(|k| at.1 - 6.0 + k * LABEL_H).find(|&y| free(y)).unwrap_or(at.1 - 6.0);
            placed.push(Rect { x, y, w: width, h: LABEL_H });
            s.push(Shape::Text { at: (x, y), text, color: color_of(&r.variant), scale: 1, centered: false });
        }
    }
    let legend = "blue f32, green fp16, orange int8, black original; filled unpruned, hollow pruned; circle ORT, square tract; red: Pareto front";
    s.push(Shape::Text { at: (WIDTH as f64 / 2.0, HEIGHT as f64 - 16.0), text: legend.into(), color: BLACK, scale: 1, centered: true });
    s
}

pub fn svg(rows: &[Row], title: &str) -> String {
    canvas::svg(&layout(rows, title), WIDTH, HEIGHT)
}

pub fn png(rows: &[Row], title: &str) -> Result<Vec<u8>> {
    canvas::png(&layout(rows, title), WIDTH, HEIGHT)
}
