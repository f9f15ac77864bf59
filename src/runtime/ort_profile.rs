//! Where ONNX Runtime spends a run: its own profiler's per-kernel times.
//!
//! ORT names the nodes it runs after its rewrites, not the model's: a QDQ group fused into
//! QLinearConv keeps the Conv's name, and its layout pass (NCHW -> NHWC for integer kernels)
//! appends `_token_<n>`. [`KernelTime::source`] undoes that suffix; a time whose name matches
//! no node of the model belongs to a node ORT made up (a Transpose, a reorder) and is kept
//! under its own name.

use super::Runtime;
use crate::onnx::proto::ModelProto;
use crate::tensor::Tensor;
use anyhow::{Context, Result};
use std::collections::HashMap;

/// Profiled runs after warm-up; the median per kernel is kept.
const RUNS: usize = 5;
/// Runs left out of the medians: the first runs pay for allocation and kernel selection.
const WARMUP: usize = 2;

#[derive(Clone, Debug, serde::Serialize)]
pub struct KernelTime {
    /// The node's name in ORT's optimized graph.
    pub name: String,
    /// The kernel ORT ran (`QLinearConv`, `Conv`, `Transpose`, ...).
    pub op: String,
    pub ms: f64,
}

impl KernelTime {
    /// The model node this kernel runs, by name (the layout pass's `_token_<n>` removed).
    pub fn source(&self) -> &str {
        match self.name.rsplit_once("_token_") {
            Some((head, n)) if !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()) => head,
            _ => &self.name,
        }
    }
}

pub struct Profile {
    pub kernels: Vec<KernelTime>,
    /// Median of the whole runs, as the profiler timed them.
    pub run_ms: f64,
}

/// Profiles `model` on `inputs` with `threads` intra-op threads (ORT's full optimizations).
pub fn profile(model: &ModelProto, inputs: &[(String, Tensor)], threads: usize) -> Result<Profile> {
    static SEQ: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
    let prefix = std::env::temp_dir().join(format!("pdi-compile-profile-{}-{}", std::process::id(), SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed)));
    let mut rt = super::ort_runtime::OrtRuntime::profiled(model, threads, &prefix)?;
    for _ in 0..WARMUP + RUNS {
        rt.run(inputs)?;
    }
    let path = rt.end_profiling()?;
    let text = std::fs::read_to_string(&path).with_context(|| format!("reading ONNX Runtime's profile {path}"));
    let _ = std::fs::remove_file(&path);
    parse(&text?, WARMUP)
}

/// Per-kernel medians from ORT's profile JSON (a list of trace events), skipping each
/// kernel's first `skip` runs.
fn parse(text: &str, skip: usize) -> Result<Profile> {
    let events: Vec<serde_json::Value> = serde_json::from_str(text).context("ONNX Runtime's profile is not a JSON list of events")?;
    let mut per: HashMap<(String, String), Vec<f64>> = HashMap::new();
    let mut order: Vec<(String, String)> = Vec::new();
    let mut runs = Vec::new();
    for e in &events {
        let (Some(name), Some(dur)) = (e["name"].as_str(), e["dur"].as_f64()) else { continue };
        if name == "model_run" {
            runs.push(dur / 1e3);
        } else if let (Some("Node"), Some(node)) = (e["cat"].as_str(), name.strip_suffix("_kernel_time")) {
            let key = (node.to_string(), e["args"]["op_name"].as_str().unwrap_or("").to_string());
            if !per.contains_key(&key) {
                order.push(key.clone());
            }
            per.entry(key).or_default().push(dur / 1e3);
        }
    }
    let kernels = order.into_iter().map(|k| {
        let ms = crate::metrics::order::median(per[&k].iter().skip(skip).copied().collect());
        KernelTime { name: k.0, op: k.1, ms }
    });
    Ok(Profile { kernels: kernels.collect(), run_ms: crate::metrics::order::median(runs.into_iter().skip(skip).collect()) })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_suffix_is_removed_and_other_names_kept() {
        let k = |n: &str| KernelTime { name: n.into(), op: String::new(), ms: 0.0 };
        assert_eq!(k("/enc1/body/body.0/Conv_token_9").source(), "/enc1/body/body.0/Conv");
        assert_eq!(k("/a/Conv").source(), "/a/Conv");
        assert_eq!(k("x_token_").source(), "x_token_");
        assert_eq!(k("x_token_a1").source(), "x_token_a1");
    }

    #[test]
    fn medians_skip_warmup_runs() {
        let ev = |name: &str, dur: f64| serde_json::json!({"cat": "Node", "name": format!("{name}_kernel_time"), "dur": dur, "args": {"op_name": "Conv"}});
        let mut events = vec![];
        for d in [900.0, 1000.0, 3000.0, 2000.0] {
            events.push(ev("a", d * 1e3));
            events.push(serde_json::json!({"cat": "Session", "name": "model_run", "dur": d * 2e3}));
        }
        let p = parse(&serde_json::to_string(&events).unwrap(), 1).unwrap();
        assert_eq!(p.kernels.len(), 1);
        assert_eq!(p.kernels[0].ms, 2000.0);
        assert_eq!(p.run_ms, 4000.0);
    }
}
