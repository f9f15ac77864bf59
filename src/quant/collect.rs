//! Range collection: the float model runs on the calibration frames with the values to
//! quantize exposed as outputs, and every value streams into its histogram (and, for
//! convolution inputs, per-channel means for bias correction).

use super::histogram::Histogram;
use crate::onnx::edit::expose_outputs;
use crate::onnx::proto::ModelProto;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::tensor::Tensor;
use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use ort::session::builder::GraphOptimizationLevel;
use rayon::prelude::*;
use std::collections::HashMap;

#[derive(Default)]
pub struct Statistics {
    pub histograms: HashMap<String, Histogram>,
    /// Mean per channel (NCHW, batch 1) over all frames, for the values asked for.
    pub channel_means: HashMap<String, Vec<f64>>,
    /// Wall time of the whole collection, and of the statistics alone (inside it).
    pub seconds: f64,
    pub statistics_seconds: f64,
}

/// Mean seconds of one plain run of `model` over the first `max_frames` of `feeds`, on
/// `threads` threads (first run included, as in the collection): what calibration is
/// measured against.
pub fn plain_seconds_per_frame(model: &ModelProto, feeds: &[Vec<(String, Tensor)>], threads: usize, max_frames: usize) -> Result<f64> {
    use crate::runtime::Runtime;
    let mut rt = OrtRuntime::with_options(model, GraphOptimizationLevel::Level3, threads)?;
    let frames = &feeds[..feeds.len().min(max_frames.max(1))];
    let t = std::time::Instant::now();
    for f in frames {
        rt.run(f)?;
    }
    Ok(t.elapsed().as_secs_f64() / frames.len().max(1) as f64)
}

/// Histograms of `values` and channel means of `per_channel` (value -> channel count) over
/// `feeds`, each frame run once. Graph inputs among them are read from the feeds.
pub fn statistics(model: &ModelProto, values: &[String], per_channel: &HashMap<String, usize>, feeds: &[Vec<(String, Tensor)>], threads: usize) -> Result<Statistics> {
    let inputs: Vec<&str> = model.graph.iter().flat_map(|g| &g.input).map(|v| v.name.as_str()).collect();
    let exposed: Vec<String> = values.iter().chain(per_channel.keys()).filter(|v| !inputs.contains(&v.as_str())).cloned().collect();
    let mut rt = OrtRuntime::with_options(&expose_outputs(model, &exposed), GraphOptimizationLevel::Level3, threads)?;
    let mut hists: HashMap<String, Histogram> = values.iter().map(|v| (v.clone(), Histogram::default())).collect();
    let mut sums: HashMap<String, (usize, Vec<f64>)> = per_channel.iter().map(|(v, &c)| (v.clone(), (c.max(1), vec![0.0; c.max(1)]))).collect();
    let pb = ProgressBar::new(feeds.len() as u64);
    pb.set_style(ProgressStyle::with_template("calibrating ranges [{bar:30}] {pos}/{len} frames").expect("valid template").progress_chars("=> "));
    let started = std::time::Instant::now();
    let mut statistics_seconds = 0.0;
    for f in feeds {
        let mut fill = |outputs: &[(&str, &[f32])]| {
            let t = std::time::Instant::now();
            let by_name: HashMap<&str, &[f32]> = outputs.iter().copied().chain(f.iter().filter_map(|(n, t)| Some((n.as_str(), t.as_f32()?)))).collect();
            hists.par_iter_mut().for_each(|(name, h)| {
                if let Some(v) = by_name.get(name.as_str()) {
                    h.add(v);
                }
            });
            sums.par_iter_mut().for_each(|(name, (c, acc))| {
                if let Some(v) = by_name.get(name.as_str()) {
                    let plane = (v.len() / *c).max(1);
                    for (k, chunk) in v.chunks(plane).enumerate().take(*c) {
                        // f32 partial sums over short runs (vectorized), f64 across them.
                        let total: f64 = chunk.chunks(256).map(|r| r.iter().sum::<f32>() as f64).sum();
                        acc[k] += total / plane as f64;
                    }
                }
            });
            statistics_seconds += t.elapsed().as_secs_f64();
        };
        if exposed.is_empty() {
            fill(&[]);
        } else {
            rt.visit_f32(f, fill)?;
        }
        pb.inc(1);
    }
    pb.finish_and_clear();
    let n = feeds.len().max(1) as f64;
    let channel_means = sums.into_iter().map(|(v, (_, acc))| (v, acc.into_iter().map(|s| s / n).collect())).collect();
    Ok(Statistics { histograms: hists, channel_means, seconds: started.elapsed().as_secs_f64(), statistics_seconds })
}
