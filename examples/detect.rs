//! Loads an artifact pdi-compile built and prints what it detects in a folder of frames:
//!
//!     cargo run --release --example detect -- ARTIFACT_DIR FRAMES_DIR
//!
//! The same code path as `pdi-compile run`: the artifact says how to pre-process, which
//! engine to use and how to decode its head.

use pdi_compile::deploy::{image, Detector, Image};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let [_, artifact, frames] = &args[..] else {
        anyhow::bail!("usage: detect ARTIFACT_DIR FRAMES_DIR");
    };
    let mut detector = Detector::load(artifact)?;
    println!("{} on {:?}, {} thread(s)", artifact, detector.engine, detector.threads);
    for path in image::list(frames.as_ref())? {
        let frame = Image::read(&path)?;
        for d in detector.detect(&frame)? {
            let [x1, y1, x2, y2] = d.bbox;
            println!("{} {} {:.3} {x1:.1} {y1:.1} {x2:.1} {y2:.1}", path.display(), detector.class_name(d.class), d.score);
        }
    }
    Ok(())
}
