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

/// Sessions taking calibration frames in turns (one runs while the other is summarized).
const SESSIONS: usize = 2;

/// Whose turn it is to add its frame's summary, in frame order; `abort` wakes every waiter
/// when a worker fails, so none waits for a frame that will never come.
#[derive(Default)]
struct Turn {
    state: std::sync::Mutex<(usize, bool)>,
    changed: std::sync::Condvar,
}

impl Turn {
    fn wait_for(&self, frame: usize) -> Result<()> {
        let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
        while s.0 != frame && !s.1 {
            s = self.changed.wait(s).unwrap_or_else(|e| e.into_inner());
        }
        if s.1 {
            anyhow::bail!("calibration stopped: another frame failed");
        }
        Ok(())
    }

    fn pass(&self, next: usize) {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).0 = next;
        self.changed.notify_all();
    }

    fn abort(&self) {
        self.state.lock().unwrap_or_else(|e| e.into_inner()).1 = true;
        self.changed.notify_all();
    }
}

/// What one value accumulates: its histogram, its per-channel sums, or both (from one pass).
#[derive(Default)]
struct Accumulator {
    histogram: Option<Histogram>,
    /// Channel count and per-channel sums of plane means.
    channels: Option<(usize, Vec<f64>)>,
}

impl Accumulator {
    fn add(&mut self, v: &[f32]) {
        match (&mut self.histogram, &mut self.channels) {
            (Some(h), Some((c, acc))) => {
                for (a, s) in acc.iter_mut().zip(h.add_planes(v, *c)) {
                    *a += s;
                }
            }
            (Some(h), None) => h.add(v),
            (None, Some((c, acc))) => {
                let plane = (v.len() / *c).max(1);
                for (k, chunk) in v.chunks(plane).enumerate().take(*c) {
                    // f32 partial sums over short runs (vectorized), f64 across them.
                    let total: f64 = chunk.chunks(256).map(|r| r.iter().sum::<f32>() as f64).sum();
                    acc[k] += total / plane as f64;
                }
            }
            (None, None) => {}
        }
    }
}

/// Histograms of `values` and channel means of `per_channel` (value -> channel count) over
/// `feeds`, each frame run once. Graph inputs among them are read from the feeds. A value
/// wanting both is read once: its plane sums come from the histogram's own pass.
pub fn statistics(model: &ModelProto, values: &[String], per_channel: &HashMap<String, usize>, feeds: &[Vec<(String, Tensor)>], threads: usize) -> Result<Statistics> {
    let inputs: Vec<&str> = model.graph.iter().flat_map(|g| &g.input).map(|v| v.name.as_str()).collect();
    let mut acc: HashMap<String, Accumulator> = HashMap::new();
    for v in values {
        acc.entry(v.clone()).or_default().histogram = Some(Histogram::default());
    }
    for (v, &c) in per_channel {
        acc.entry(v.clone()).or_default().channels = Some((c.max(1), vec![0.0; c.max(1)]));
    }
    let exposed: Vec<String> = acc.keys().filter(|v| !inputs.contains(&v.as_str())).cloned().collect();
    let observed = expose_outputs(model, &exposed);
    let pb = ProgressBar::new(feeds.len() as u64);
    pb.set_style(ProgressStyle::with_template("calibrating ranges [{bar:30}] {pos}/{len} frames").expect("valid template").progress_chars("=> "));
    let started = std::time::Instant::now();
    // Two sessions take the frames in turns, so that one runs the model while the other's
    // outputs are summarized; summaries still go in strictly in frame order, because a
    // histogram's bins depend on the order its values arrive in.
    let sessions = if exposed.is_empty() { 0 } else { SESSIONS.min(feeds.len()) };
    let mut runtimes = (0..sessions).map(|_| OrtRuntime::sharing_cores(&observed, threads)).collect::<Result<Vec<_>>>()?;
    let turn = Turn::default();
    let shared = std::sync::Mutex::new((acc, 0.0f64));
    let summarize = |f: &[(String, Tensor)], outputs: &[(&str, &[f32])]| {
        let t = std::time::Instant::now();
        let by_name: HashMap<&str, &[f32]> = outputs.iter().copied().chain(f.iter().filter_map(|(n, t)| Some((n.as_str(), t.as_f32()?)))).collect();
        let mut guard = shared.lock().unwrap_or_else(|e| e.into_inner());
        guard.0.par_iter_mut().for_each(|(name, a)| {
            if let Some(v) = by_name.get(name.as_str()) {
                a.add(v);
            }
        });
        guard.1 += t.elapsed().as_secs_f64();
        pb.inc(1);
    };
    if sessions == 0 {
        feeds.iter().for_each(|f| summarize(f, &[]));
    } else {
        std::thread::scope(|scope| -> Result<()> {
            let workers: Vec<_> = runtimes
                .iter_mut()
                .enumerate()
                .map(|(k, rt)| {
                    let (turn, summarize) = (&turn, &summarize);
                    scope.spawn(move || -> Result<()> {
                        for i in (k..feeds.len()).step_by(sessions) {
                            let ran = rt.visit_f32(&feeds[i], |outputs| {
                                turn.wait_for(i)?;
                                summarize(&feeds[i], outputs);
                                turn.pass(i + 1);
                                Ok(())
                            });
                            if let Err(e) = ran.and_then(|r| r) {
                                turn.abort();
                                return Err(e);
                            }
                        }
                        Ok(())
                    })
                })
                .collect();
            let results: Vec<Result<()>> = workers.into_iter().map(|w| w.join().unwrap_or_else(|_| Err(anyhow::anyhow!("a calibration worker panicked")))).collect();
            // The worker that failed first says why; the other only says it stopped.
            let mut errors: Vec<anyhow::Error> = results.into_iter().filter_map(Result::err).collect();
            errors.sort_by_key(|e| e.to_string().starts_with("calibration stopped"));
            errors.into_iter().next().map_or(Ok(()), Err)
        })?;
    }
    pb.finish_and_clear();
    let (acc, statistics_seconds) = shared.into_inner().unwrap_or_else(|e| e.into_inner());
    let n = feeds.len().max(1) as f64;
    let (mut histograms, mut channel_means) = (HashMap::new(), HashMap::new());
    for (v, a) in acc {
        if let Some((_, sums)) = a.channels {
            channel_means.insert(v.clone(), sums.into_iter().map(|s| s / n).collect());
        }
        if let Some(h) = a.histogram {
            histograms.insert(v, h);
        }
    }
    Ok(Statistics { histograms, channel_means, seconds: started.elapsed().as_secs_f64(), statistics_seconds })
}
