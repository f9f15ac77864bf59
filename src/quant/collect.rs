//! Range collection: the float model runs on the calibration frames with the values to
//! quantize exposed as outputs, and every value streams into its histogram.

use super::histogram::Histogram;
use crate::onnx::edit::expose_outputs;
use crate::onnx::proto::ModelProto;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use ort::session::builder::GraphOptimizationLevel;
use rayon::prelude::*;
use std::collections::HashMap;

/// Histograms of `values` over `feeds`, each frame run once.
pub fn histograms(model: &ModelProto, values: &[String], feeds: &[Vec<(String, Tensor)>], threads: usize) -> Result<HashMap<String, Histogram>> {
    let mut rt = OrtRuntime::with_options(&expose_outputs(model, values), GraphOptimizationLevel::Level3, threads)?;
    let mut hists: HashMap<String, Histogram> = values.iter().map(|v| (v.clone(), Histogram::default())).collect();
    let pb = ProgressBar::new(feeds.len() as u64);
    pb.set_style(ProgressStyle::with_template("calibrating ranges [{bar:30}] {pos}/{len} frames").expect("valid template").progress_chars("=> "));
    for f in feeds {
        let outputs = rt.run(f)?;
        let by_name: HashMap<&str, &Tensor> = outputs.iter().map(|(n, t)| (n.as_str(), t)).collect();
        hists.par_iter_mut().for_each(|(name, h)| {
            if let Some(v) = by_name.get(name.as_str()).and_then(|t| t.as_f32()) {
                h.add(v);
            }
        });
        pb.inc(1);
    }
    pb.finish_and_clear();
    Ok(hists)
}
