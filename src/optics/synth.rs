//! Clean synthetic thermal scenes with YOLO labels for the six M3FD classes.
//!
//! A cool sky over warmer ground with a perspective road, low-frequency texture, and warm
//! objects standing on the ground plane: their pixel size follows their distance (objects
//! near the horizon are small, many targets are tiny), they are drawn far to near so nearer
//! ones occlude, and a box is labelled only when at least `MIN_VISIBLE` of it stays visible.
//! Values are normalized radiance in [0, 1]. Deterministic in the seed.

use super::rng::Rng;
use crate::metrics::coco_map::Truth;

pub const CLASSES: [&str; 6] = ["People", "Car", "Bus", "Motorcycle", "Lamp", "Truck"];

/// An object with less of its area visible than this is not labelled (as annotators do).
const MIN_VISIBLE: f64 = 0.3;
/// Camera height over the ground, metres: sets how fast objects shrink toward the horizon.
const CAMERA_HEIGHT_M: f64 = 6.0;

pub struct Scene {
    pub width: usize,
    pub height: usize,
    pub pixels: Vec<f32>,
    pub labels: Vec<Truth>,
}

/// Class size (width, height in metres) and temperature range (normalized).
fn class_props(class: usize) -> ((f64, f64), (f64, f64)) {
    match class {
        0 => ((0.55, 1.75), (0.62, 0.80)), // People
        1 => ((4.4, 1.5), (0.50, 0.70)),   // Car
        2 => ((11.0, 3.2), (0.48, 0.62)),  // Bus
        3 => ((1.9, 1.3), (0.58, 0.78)),   // Motorcycle (with rider)
        4 => ((0.5, 6.0), (0.40, 0.55)),   // Lamp (pole; the head is hotter)
        _ => ((8.0, 3.6), (0.50, 0.66)),   // Truck
    }
}

/// Soft inside test: 1 inside, 0 outside, a one-pixel ramp at the edge (anti-aliasing).
fn ramp(d: f64) -> f64 {
    (0.5 - d).clamp(0.0, 1.0)
}

struct Canvas<'a> {
    w: usize,
    h: usize,
    px: &'a mut [f32],
    owner: &'a mut [u16],
}

impl Canvas<'_> {
    /// Mixes temperature t into pixel i with coverage a; the pixel belongs to `id` when mostly covered.
    fn blend(&mut self, i: usize, a: f64, t: f64, id: u16) {
        if a > 0.0 {
            self.px[i] = (self.px[i] as f64 * (1.0 - a) + t * a) as f32;
            if a >= 0.5 {
                self.owner[i] = id;
            }
        }
    }

    /// Draws an axis-aligned box (rounded by `round` px) of temperature t, owned by `id`.
    fn rect(&mut self, x0: f64, y0: f64, x1: f64, y1: f64, t: f64, id: u16) {
        let (xa, xb) = ((x0.floor().max(0.0)) as usize, (x1.ceil().min(self.w as f64)) as usize);
        let (ya, yb) = ((y0.floor().max(0.0)) as usize, (y1.ceil().min(self.h as f64)) as usize);
        for y in ya..yb {
            for x in xa..xb {
                let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
                let d = (x0 - cx).max(cx - x1).max(y0 - cy).max(cy - y1);
                self.blend(y * self.w + x, ramp(d + 0.5), t, id);
            }
        }
    }

    fn ellipse(&mut self, cx: f64, cy: f64, rx: f64, ry: f64, t: f64, id: u16) {
        let (xa, xb) = (((cx - rx).floor().max(0.0)) as usize, ((cx + rx).ceil().min(self.w as f64)) as usize);
        let (ya, yb) = (((cy - ry).floor().max(0.0)) as usize, ((cy + ry).ceil().min(self.h as f64)) as usize);
        for y in ya..yb {
            for x in xa..xb {
                let (u, v) = ((x as f64 + 0.5 - cx) / rx.max(0.5), (y as f64 + 0.5 - cy) / ry.max(0.5));
                let d = ((u * u + v * v).sqrt() - 1.0) * rx.min(ry).max(0.5);
                self.blend(y * self.w + x, ramp(d + 0.5), t, id);
            }
        }
    }
}

/// Draws one object with its bottom centre at (x, y) and scale `s` px/m; returns its box.
fn draw_object(c: &mut Canvas, class: usize, x: f64, y: f64, s: f64, t: f64, id: u16, rng: &mut Rng) -> [f64; 4] {
    let ((wm, hm), _) = class_props(class);
    let (w, h) = (wm * s * rng.range(0.85, 1.15), hm * s * rng.range(0.9, 1.1));
    let (x0, y0, x1) = (x - w / 2.0, y - h, x + w / 2.0);
    match class {
        0 => {
            c.ellipse(x, y - h * 0.42, w * 0.5, h * 0.42, t, id);
            c.ellipse(x, y - h * 0.9, w * 0.3, h * 0.1, t + 0.05, id);
        }
        1 | 5 | 2 => {
            let cab = if class == 1 { 0.45 } else { 0.0 };
            c.rect(x0, y0 + h * cab, x1, y - h * 0.15, t, id);
            if class == 1 {
                c.rect(x0 + w * 0.2, y0, x1 - w * 0.25, y0 + h * 0.5, t - 0.05, id);
            }
            if class == 5 {
                c.rect(x1 - w * 0.25, y0 + h * 0.25, x1, y - h * 0.15, t + 0.04, id); // cab, engine heat
            }
            if class == 2 {
                for k in 0..5 {
                    let wx = x0 + w * (0.08 + 0.18 * k as f64);
                    c.rect(wx, y0 + h * 0.15, wx + w * 0.12, y0 + h * 0.45, t - 0.08, id); // windows are cooler
                }
            }
            for wx in [x0 + w * 0.18, x1 - w * 0.18] {
                c.ellipse(wx, y - h * 0.15, (h * 0.16).max(0.6), (h * 0.16).max(0.6), t + 0.08, id); // warm tyres
            }
        }
        3 => {
            c.ellipse(x, y - h * 0.25, w * 0.5, h * 0.22, t, id);
            c.ellipse(x, y - h * 0.7, w * 0.18, h * 0.3, t + 0.05, id);
        }
        _ => {
            c.rect(x - w * 0.1, y0 + h * 0.05, x + w * 0.1, y, t - 0.05, id);
            c.ellipse(x, y0 + h * 0.05, w * 0.5, (h * 0.05).max(0.7), t + 0.25, id);
        }
    }
    [x0.max(0.0), y0.max(0.0), x1.min(c.w as f64), y.min(c.h as f64)]
}

pub fn scene(width: usize, height: usize, seed: u64) -> Scene {
    let mut rng = Rng::new(seed);
    let (w, h) = (width as f64, height as f64);
    let horizon = rng.range(0.28, 0.5) * h;
    let road_half = rng.range(0.15, 0.35) * w; // road half-width at the bottom edge
    let road_cx = rng.range(0.35, 0.65) * w;
    let (sky_t, ground_t, road_t) = (rng.range(0.05, 0.2), rng.range(0.3, 0.42), rng.range(0.38, 0.5));
    let waves: Vec<[f64; 4]> = (0..4).map(|_| [rng.range(1.0, 9.0), rng.range(1.0, 7.0), rng.range(0.0, 6.3), rng.range(0.005, 0.02)]).collect();
    let mut px = vec![0f32; width * height];
    for yy in 0..height {
        let y = yy as f64 + 0.5;
        for xx in 0..width {
            let x = xx as f64 + 0.5;
            let mut t = if y < horizon {
                sky_t + 0.06 * y / horizon
            } else {
                let depth = (y - horizon) / (h - horizon);
                let on_road = (x - road_cx).abs() < road_half * depth;
                (if on_road { road_t } else { ground_t }) + 0.05 * depth
            };
            for wv in &waves {
                t += wv[3] * (std::f64::consts::TAU * (wv[0] * x / w + wv[1] * y / h) + wv[2]).sin();
            }
            px[yy * width + xx] = t as f32;
        }
    }
    let mut owner = vec![0u16; width * height];
    let n = 3 + (rng.uniform() * 14.0) as usize;
    // Bottom positions biased toward the horizon: many distant, small targets.
    let mut objects: Vec<(f64, f64, usize)> = (0..n)
        .map(|_| {
            let class = match rng.uniform() { u if u < 0.35 => 0, u if u < 0.65 => 1, u if u < 0.72 => 2, u if u < 0.82 => 3, u if u < 0.9 => 4, _ => 5 };
            let y = horizon + 2.0 + (h - horizon - 2.0) * rng.uniform().powf(1.8);
            (rng.range(0.02, 0.98) * w, y, class)
        })
        .collect();
    objects.sort_by(|a, b| a.1.total_cmp(&b.1)); // far first: nearer objects occlude
    let mut boxes = Vec::new();
    {
        let mut canvas = Canvas { w: width, h: height, px: &mut px, owner: &mut owner };
        for (k, &(x, y, class)) in objects.iter().enumerate() {
            let s = (y - horizon) / CAMERA_HEIGHT_M;
            let (_, (t0, t1)) = class_props(class);
            let b = draw_object(&mut canvas, class, x, y, s, rng.range(t0, t1), k as u16 + 1, &mut rng);
            boxes.push((b, class, k as u16 + 1));
        }
    }
    let mut labels = Vec::new();
    for (b, class, id) in boxes {
        let area = ((b[2] - b[0]) * (b[3] - b[1])).max(0.0);
        if area < 4.0 {
            continue;
        }
        let (x0, x1, y0, y1) = (b[0] as usize, (b[2].ceil() as usize).min(width), b[1] as usize, (b[3].ceil() as usize).min(height));
        let mine = (y0..y1).flat_map(|y| (x0..x1).map(move |x| (x, y))).filter(|&(x, y)| owner[y * width + x] == id).count() as f64;
        let drawn = (y0..y1).flat_map(|y| (x0..x1).map(move |x| (x, y))).count() as f64;
        // Shapes fill part of their box; compare with what an unoccluded one fills (~0.6).
        if mine >= MIN_VISIBLE * 0.6 * drawn.max(1.0) {
            labels.push(Truth { class, bbox: [b[0] as f32, b[1] as f32, b[2] as f32, b[3] as f32] });
        }
    }
    for v in px.iter_mut() {
        *v = v.clamp(0.0, 1.0);
    }
    Scene { width, height, pixels: px, labels }
}

/// YOLO label text: `class cx cy w h`, normalized.
pub fn yolo_text(labels: &[Truth], width: usize, height: usize) -> String {
    let (w, h) = (width as f32, height as f32);
    labels
        .iter()
        .map(|t| {
            let b = t.bbox;
            format!("{} {:.6} {:.6} {:.6} {:.6}\n", t.class, (b[0] + b[2]) / 2.0 / w, (b[1] + b[3]) / 2.0 / h, (b[2] - b[0]) / w, (b[3] - b[1]) / h)
        })
        .collect()
}
