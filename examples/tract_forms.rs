//! Two forms of one model on tract beside ONNX Runtime on the first, timed in one
//! interleaved loop (so their ratios come from the same run), on 2 threads:
//!   cargo run --release --example tract_forms -- MODEL.onnx TRACT_FORM.onnx RUNS
//! e.g. a compile against the same compile with `--target tract` (its column tiles).
use pdi_compile::runtime::{ort_runtime::OrtRuntime, tract_runtime::TractRuntime, Runtime};
use pdi_compile::runtime::latency::interleaved;
fn main() -> anyhow::Result<()> {
    let a: Vec<String> = std::env::args().collect();
    let load = |p: &str| pdi_compile::onnx::io::load(std::path::Path::new(p)).map(|l| l.model);
    let (m0, m1) = (load(&a[1])?, load(&a[2])?);
    let runs: usize = a[3].parse()?;
    let g = m0.graph.as_ref().unwrap();
    let input = &g.input[0];
    let shape = pdi_compile::ir::shapes::declared(input).static_shape().unwrap();
    let frame = pdi_compile::calib_frames::calibration_frames(None, 1, shape[2], shape[3], 0)?.frames.remove(0).image;
    let feeds = vec![(input.name.clone(), frame)];
    let mut o = OrtRuntime::with_options(&m0, ort::session::builder::GraphOptimizationLevel::Level3, 2)?;
    let mut t0 = TractRuntime::new(&m0, &feeds, 2)?;
    let mut t1 = TractRuntime::new(&m1, &feeds, 2)?;
    let lat = interleaved(&mut [("ort".into(), &mut o as &mut dyn Runtime, feeds.clone()), ("tract-whole".into(), &mut t0, feeds.clone()), ("tract-tiled".into(), &mut t1, feeds.clone())], runs)?;
    for l in &lat { println!("{} median {:.1} min {:.1}", l.name, l.median_ms, l.min_ms); }
    println!("ratio whole {:.3} tiled {:.3}", lat[1].median_ms / lat[0].median_ms, lat[2].median_ms / lat[0].median_ms);
    Ok(())
}
