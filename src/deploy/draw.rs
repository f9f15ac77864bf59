//! Pictures of detections: the frame (16-bit and float frames stretched between their 1st and
//! 99th percentiles, as thermal viewers show them; 8-bit frames as stored), each box outlined
//! in its class's colour with its name and score above it, and a contact sheet of several.

use crate::canvas::{paint, Shape};
use crate::detect::Detection;
use super::Image;
use image::RgbImage;

/// Box outline width in pixels.
pub const LINE: u32 = 2;
/// Boxes only one of two compared models found.
pub const ONLY_ONE: [u8; 3] = [255, 0, 255];

/// Class colours (distinct on a gray frame; none is gray or magenta).
const PALETTE: [[u8; 3]; 8] = [[255, 56, 56], [44, 153, 168], [255, 178, 29], [72, 249, 10], [0, 194, 255], [255, 112, 31], [146, 204, 23], [52, 69, 147]];

pub fn class_colour(class: usize) -> [u8; 3] {
    PALETTE[class % PALETTE.len()]
}

/// The frame as gray pixels: integer 8-bit as stored, everything else stretched.
pub fn gray(frame: &Image) -> RgbImage {
    let (lo, hi) = if frame.bits == 8 { (0.0, 1.0) } else { percentiles(&frame.data) };
    let scale = if hi > lo { 255.0 / (hi - lo) } else { 0.0 };
    let px: Vec<u8> = frame.data.iter().flat_map(|&v| [((v - lo) * scale).round().clamp(0.0, 255.0) as u8; 3]).collect();
    RgbImage::from_raw(frame.width as u32, frame.height as u32, px).expect("width x height x 3 bytes")
}

/// The 1st and 99th percentiles (by sorting a copy: frames are small next to a model run).
fn percentiles(v: &[f32]) -> (f32, f32) {
    let mut s: Vec<f32> = v.to_vec();
    s.sort_by(f32::total_cmp);
    let at = |q: f64| s[((s.len() - 1) as f64 * q).round() as usize];
    (at(0.01), at(0.99))
}

/// The shapes of one detection: its outline in `colour`, a filled tag above it (inside, at the
/// frame's top edge; moved left to stay inside a frame `width` wide) with `label` in white.
pub fn boxed(d: &Detection, label: &str, colour: [u8; 3], width: u32) -> Vec<Shape> {
    let [x1, y1, x2, y2] = d.bbox.map(|v| v.round() as f64);
    let w = LINE as f64;
    let mut s = vec![
        Shape::Line { from: (x1, y1), to: (x2, y1), color: colour, width: w },
        Shape::Line { from: (x1, y2 - w + 1.0), to: (x2, y2 - w + 1.0), color: colour, width: w },
        Shape::Line { from: (x1, y1), to: (x1, y2), color: colour, width: w },
        Shape::Line { from: (x2 - w + 1.0, y1), to: (x2 - w + 1.0, y2), color: colour, width: w },
    ];
    let tag_w = 8.0 * label.chars().count() as f64 + 4.0;
    let top = if y1 >= 11.0 { y1 - 11.0 } else { y1 + w };
    let left = x1.min(width as f64 - tag_w).max(0.0);
    s.push(Shape::Fill { at: (left, top), size: (tag_w, 11.0), color: colour });
    s.push(Shape::Text { at: (left + 2.0, top + 9.5), text: label.to_string(), color: [255, 255, 255], scale: 1, centered: false });
    s
}

/// The frame with `dets` drawn; a detection whose index is in `only` is drawn in
/// [`ONLY_ONE`] (found by this model and not by the one it is compared with).
pub fn annotate(frame: &Image, dets: &[Detection], names: &[String], only: &[usize]) -> RgbImage {
    let mut img = gray(frame);
    // Weakest first, so the best box's tag is on top.
    let mut order: Vec<usize> = (0..dets.len()).collect();
    order.sort_by(|&a, &b| dets[a].score.total_cmp(&dets[b].score));
    for i in order {
        let d = &dets[i];
        let name = names.get(d.class).map_or_else(|| d.class.to_string(), String::clone);
        let (colour, label) = if only.contains(&i) { (ONLY_ONE, format!("{name} {:.2} only", d.score)) } else { (class_colour(d.class), format!("{name} {:.2}", d.score)) };
        let shapes = boxed(d, &label, colour, img.width());
        paint(&mut img, &shapes);
    }
    img
}

/// Pictures side by side under their titles, on one canvas.
pub fn side_by_side(pictures: &[(&str, &RgbImage)]) -> RgbImage {
    let title = 14u32;
    let gap = 8u32;
    let w: u32 = pictures.iter().map(|(_, p)| p.width()).sum::<u32>() + gap * pictures.len().saturating_sub(1) as u32;
    let h = pictures.iter().map(|(_, p)| p.height()).max().unwrap_or(0) + title;
    let mut out = RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let mut x = 0;
    for (name, p) in pictures {
        image::imageops::overlay(&mut out, *p, x as i64, title as i64);
        paint(&mut out, &[Shape::Text { at: (x as f64 + 2.0, 11.0), text: name.to_string(), color: [0, 0, 0], scale: 1, centered: false }]);
        x += p.width() + gap;
    }
    out
}

/// A grid of pictures, each scaled to at most `tile` pixels wide, captioned; `columns` wide.
pub fn contact_sheet(pictures: &[(String, RgbImage)], columns: usize, tile: u32) -> RgbImage {
    let columns = columns.clamp(1, pictures.len().max(1));
    let rows = pictures.len().div_ceil(columns).max(1);
    let scaled: Vec<(String, RgbImage)> = pictures
        .iter()
        .map(|(n, p)| {
            let f = (tile as f64 / p.width() as f64).min(1.0);
            let (w, h) = (((p.width() as f64 * f).round() as u32).max(1), ((p.height() as f64 * f).round() as u32).max(1));
            (n.clone(), if f < 1.0 { image::imageops::resize(p, w, h, image::imageops::FilterType::Triangle) } else { p.clone() })
        })
        .collect();
    let cell_w = scaled.iter().map(|(_, p)| p.width()).max().unwrap_or(1) + 4;
    let cell_h = scaled.iter().map(|(_, p)| p.height()).max().unwrap_or(1) + 16;
    let mut out = RgbImage::from_pixel(cell_w * columns as u32, cell_h * rows as u32, image::Rgb([255, 255, 255]));
    for (i, (name, p)) in scaled.iter().enumerate() {
        let (x, y) = ((i % columns) as u32 * cell_w + 2, (i / columns) as u32 * cell_h);
        image::imageops::overlay(&mut out, p, x as i64, y as i64 + 14);
        let caption: String = name.chars().take((cell_w as usize - 4) / 8).collect();
        paint(&mut out, &[Shape::Text { at: (x as f64, y as f64 + 11.0), text: caption, color: [0, 0, 0], scale: 1, centered: false }]);
    }
    out
}
