//! Plots drawn once as shapes in pixels, then written as SVG (text left to the viewer's
//! fonts) and as PNG (text from an 8x8 bitmap font compiled in, so no font files or
//! fontconfig are needed on the machine that renders).

use anyhow::Result;

#[derive(Clone)]
pub enum Shape {
    /// A filled rectangle, `at` its top-left corner.
    Fill { at: (f64, f64), size: (f64, f64), color: [u8; 3] },
    Line { from: (f64, f64), to: (f64, f64), color: [u8; 3], width: f64 },
    Marker { at: (f64, f64), radius: f64, color: [u8; 3], square: bool, filled: bool },
    /// `scale` 1 = 8 px glyphs; anchored at the left end of the baseline unless `centered`.
    Text { at: (f64, f64), text: String, color: [u8; 3], scale: u32, centered: bool },
}

pub fn hex(c: [u8; 3]) -> String {
    format!("#{:02x}{:02x}{:02x}", c[0], c[1], c[2])
}

fn escape(t: &str) -> String {
    t.replace('&', "&amp;").replace('<', "&lt;").replace('>', "&gt;")
}

pub fn svg(shapes: &[Shape], width: u32, height: u32) -> String {
    let mut out = format!("<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{width}\" height=\"{height}\" viewBox=\"0 0 {width} {height}\" font-family=\"monospace\">\n<rect width=\"100%\" height=\"100%\" fill=\"white\"/>\n");
    for shape in shapes.iter().cloned() {
        out += &match shape {
            Shape::Fill { at, size, color } => format!("<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" fill=\"{}\"/>\n", at.0, at.1, size.0, size.1, hex(color)),
            Shape::Line { from, to, color, width } => format!("<line x1=\"{:.1}\" y1=\"{:.1}\" x2=\"{:.1}\" y2=\"{:.1}\" stroke=\"{}\" stroke-width=\"{width}\"/>\n", from.0, from.1, to.0, to.1, hex(color)),
            Shape::Marker { at, radius, color, square, filled } => {
                let paint = if filled { format!("fill=\"{}\"", hex(color)) } else { format!("fill=\"none\" stroke=\"{}\" stroke-width=\"2\"", hex(color)) };
                if square {
                    format!("<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{:.1}\" height=\"{:.1}\" {paint}/>\n", at.0 - radius, at.1 - radius, 2.0 * radius, 2.0 * radius)
                } else {
                    format!("<circle cx=\"{:.1}\" cy=\"{:.1}\" r=\"{radius}\" {paint}/>\n", at.0, at.1)
                }
            }
            Shape::Text { at, text, color, scale, centered } => {
                let anchor = if centered { " text-anchor=\"middle\"" } else { "" };
                format!("<text x=\"{:.1}\" y=\"{:.1}\" font-size=\"{}\" fill=\"{}\"{anchor}>{}</text>\n", at.0, at.1, 11 * scale + 2 * (scale - 1), hex(color), escape(&text))
            }
        };
    }
    out + "</svg>\n"
}

pub fn png(shapes: &[Shape], width: u32, height: u32) -> Result<Vec<u8>> {
    let mut img = image::RgbImage::from_pixel(width, height, image::Rgb([255, 255, 255]));
    paint(&mut img, shapes);
    encode_png(&img)
}

/// PNG bytes of a picture.
pub fn encode_png(img: &image::RgbImage) -> Result<Vec<u8>> {
    let mut bytes = std::io::Cursor::new(Vec::new());
    img.write_to(&mut bytes, image::ImageFormat::Png)?;
    Ok(bytes.into_inner())
}

/// Draws `shapes` over `img` (clipped to it).
pub fn paint(img: &mut image::RgbImage, shapes: &[Shape]) {
    let (width, height) = img.dimensions();
    let mut put = |x: i64, y: i64, c: [u8; 3]| {
        if (0..width as i64).contains(&x) && (0..height as i64).contains(&y) {
            img.put_pixel(x as u32, y as u32, image::Rgb(c));
        }
    };
    for shape in shapes.iter().cloned() {
        match shape {
            Shape::Fill { at, size, color } => {
                for y in at.1.round() as i64..(at.1 + size.1).round() as i64 {
                    for x in at.0.round() as i64..(at.0 + size.0).round() as i64 {
                        put(x, y, color);
                    }
                }
            }
            Shape::Line { from, to, color, width } => {
                let steps = (to.0 - from.0).abs().max((to.1 - from.1).abs()).ceil().max(1.0) as usize;
                for i in 0..=steps {
                    let t = i as f64 / steps as f64;
                    let (x, y) = (from.0 + (to.0 - from.0) * t, from.1 + (to.1 - from.1) * t);
                    for d in 0..width.round().max(1.0) as i64 {
                        put(x.round() as i64 + if from.1 == to.1 { 0 } else { d }, y.round() as i64 + if from.1 == to.1 { d } else { 0 }, color);
                    }
                }
            }
            Shape::Marker { at, radius, color, square, filled } => {
                let r = radius.round() as i64;
                for dy in -r..=r {
                    for dx in -r..=r {
                        let inside = if square { true } else { dx * dx + dy * dy <= r * r };
                        let edge = if square { dx.abs() >= r - 1 || dy.abs() >= r - 1 } else { dx * dx + dy * dy >= (r - 2) * (r - 2) };
                        if inside && (filled || edge) {
                            put(at.0.round() as i64 + dx, at.1.round() as i64 + dy, color);
                        }
                    }
                }
            }
            Shape::Text { at, text, color, scale, centered } => {
                let s = scale as i64;
                let width = 8 * s * text.chars().count() as i64;
                let x0 = at.0.round() as i64 - if centered { width / 2 } else { 0 };
                let y0 = at.1.round() as i64 - 8 * s;
                for (i, ch) in text.chars().enumerate() {
                    let glyph = font8x8::legacy::BASIC_LEGACY.get(ch as usize).copied().unwrap_or([0; 8]);
                    for (row, bits) in glyph.iter().enumerate() {
                        for col in 0..8 {
                            if bits >> col & 1 == 1 {
                                for (sy, sx) in (0..s).flat_map(|a| (0..s).map(move |b| (a, b))) {
                                    put(x0 + 8 * s * i as i64 + col * s + sx, y0 + row as i64 * s + sy, color);
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}
