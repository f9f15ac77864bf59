//! Range collection: the float model runs on the calibration frames with the values to
//! quantize exposed as outputs, and every value streams into its histogram (and, for
//! convolution inputs, per-channel means for bias correction).

use super::histogram::{Histogram, Summary};
use crate::onnx::edit::expose_outputs;
use crate::onnx::proto::ModelProto;
use crate::runtime::ort_runtime::OrtRuntime;
use crate::tensor::Tensor;
use anyhow::Result;
use indicatif::{ProgressBar, ProgressStyle};
use ort::session::builder::GraphOptimizationLevel;
use std::collections::HashMap;

#[derive(Default)]
pub struct Statistics {
    pub histograms: HashMap<String, Histogram>,
    /// Mean per channel (NCHW, batch 1) over all frames, for the values asked for.
    pub channel_means: HashMap<String, Vec<f64>>,
    /// Wall time of the whole collection, and the time its workers spent summarizing (summed
    /// over workers, so it can exceed the part of the wall time it shares with inference).
    pub seconds: f64,
    pub statistics_seconds: f64,
}

/// Mean seconds of one plain run of `model` over the first `max_frames` of `feeds`, on
/// `threads` threads, after one untimed run: what calibration is measured against. The
/// collection's own first run (the slowest: its sessions allocate then) stays in its mean,
/// so the ratio errs against calibration.
pub fn plain_seconds_per_frame(model: &ModelProto, feeds: &[Vec<(String, Tensor)>], threads: usize, max_frames: usize) -> Result<f64> {
    use crate::runtime::Runtime;
    let mut rt = OrtRuntime::with_options(model, GraphOptimizationLevel::Level3, threads)?;
    let frames = &feeds[..feeds.len().min(max_frames.max(1))];
    if let Some(f) = frames.first() {
        rt.run(f)?;
    }
    let t = std::time::Instant::now();
    for f in frames {
        rt.run(f)?;
    }
    Ok(t.elapsed().as_secs_f64() / frames.len().max(1) as f64)
}

/// Frames in flight at most: each holds every exposed value of its frame (~0.5 GB at
/// 640x480 for the full-size v5) until it is summarized.
const MAX_WORKERS: usize = 4;

/// Whose turn it is to add its frame's summaries, in frame order; `abort` wakes every waiter
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

/// What is read from one value: its histogram, its per-channel means, or both (one pass).
#[derive(Clone, Copy, Default)]
struct Wanted {
    histogram: bool,
    channels: Option<usize>,
}

/// One frame's share of a value's statistics: computed by the frame's worker, absorbed in
/// frame order.
struct Contribution {
    summary: Option<Summary>,
    plane_means: Option<Vec<f64>>,
}

impl Wanted {
    fn contribution(&self, v: &[f32]) -> Contribution {
        match (self.histogram, self.channels) {
            (true, channels) => {
                let (summary, means) = Summary::of(v, channels.unwrap_or(1));
                Contribution { summary: Some(summary), plane_means: channels.map(|_| means) }
            }
            (false, Some(c)) => {
                let plane = (v.len() / c).max(1);
                // f32 partial sums over short runs (vectorized), f64 across them.
                let means = v.chunks(plane).take(c).map(|chunk| chunk.chunks(256).map(|r| r.iter().sum::<f32>() as f64).sum::<f64>() / plane as f64).collect();
                Contribution { summary: None, plane_means: Some(means) }
            }
            (false, None) => Contribution { summary: None, plane_means: None },
        }
    }
}

/// What one value accumulates over the frames.
struct Accumulator {
    histogram: Option<Histogram>,
    /// Per-channel sums of plane means.
    channel_sums: Option<Vec<f64>>,
}

impl Accumulator {
    fn new(w: Wanted) -> Accumulator {
        Accumulator { histogram: w.histogram.then(Histogram::default), channel_sums: w.channels.map(|c| vec![0.0; c]) }
    }

    /// The order-dependent part of adding a frame's contribution (see [`Histogram::admit`]):
    /// returns the range its bins are to be made at.
    fn admit(&mut self, c: &Contribution) -> Option<f64> {
        if let (Some(acc), Some(means)) = (&mut self.channel_sums, &c.plane_means) {
            for (a, m) in acc.iter_mut().zip(means) {
                *a += m;
            }
        }
        match (&mut self.histogram, &c.summary) {
            (Some(h), Some(s)) => Some(h.admit(s)),
            _ => None,
        }
    }
}

/// Histograms of `values` and channel means of `per_channel` (value -> channel count) over
/// `feeds`, each frame run once. Graph inputs among them are read from the feeds. A value
/// wanting both is read once: its plane sums come from the histogram's own pass.
///
/// Frames run in parallel, each on a session of its own whose worker also summarizes it; the
/// summaries are admitted in frame order, so the histograms are those of one session taking
/// the frames one by one (tested). On 2 cores at 640x480 (full-size v5) one session on both
/// cores, summarizing between runs, lost either way: its threads slept between operators
/// (runs 12% slower) or spun on into the summaries (which took 50% longer).
pub fn statistics(model: &ModelProto, values: &[String], per_channel: &HashMap<String, usize>, feeds: &[Vec<(String, Tensor)>], threads: usize) -> Result<Statistics> {
    let inputs: Vec<&str> = model.graph.iter().flat_map(|g| &g.input).map(|v| v.name.as_str()).collect();
    let mut wanted: HashMap<String, Wanted> = HashMap::new();
    for v in values {
        wanted.entry(v.clone()).or_default().histogram = true;
    }
    for (v, &c) in per_channel {
        wanted.entry(v.clone()).or_default().channels = Some(c.max(1));
    }
    let exposed: Vec<String> = wanted.keys().filter(|v| !inputs.contains(&v.as_str())).cloned().collect();
    let observed = expose_outputs(model, &exposed);
    let pb = ProgressBar::new(feeds.len() as u64);
    pb.set_style(ProgressStyle::with_template("calibrating ranges [{bar:30}] {pos}/{len} frames").expect("valid template").progress_chars("=> "));
    let started = std::time::Instant::now();
    let workers = threads.clamp(1, MAX_WORKERS).min(feeds.len()).max(1);
    let session_threads = (threads / workers).max(1);
    let turn = Turn::default();
    let acc: HashMap<String, Accumulator> = wanted.iter().map(|(v, &w)| (v.clone(), Accumulator::new(w))).collect();
    let shared = std::sync::Mutex::new((acc, 0.0f64));
    // A frame's contributions, on its worker (the outputs are released once they are read)...
    let contribute = |i: usize, outputs: &[(&str, &[f32])]| {
        let t = std::time::Instant::now();
        let by_name: HashMap<&str, &[f32]> = outputs.iter().copied().chain(feeds[i].iter().filter_map(|(n, t)| Some((n.as_str(), t.as_f32()?)))).collect();
        let contributions: Vec<(&str, Contribution)> = wanted.iter().filter_map(|(n, w)| Some((n.as_str(), w.contribution(by_name.get(n.as_str())?)))).collect();
        (contributions, t.elapsed().as_secs_f64())
    };
    // ... then, in its turn, admitted (ranges and exact statistics), and binned after it:
    // bins add up in any order once their range is fixed (Histogram::admit).
    let absorb = |i: usize, (contributions, spent): (Vec<(&str, Contribution)>, f64)| -> Result<()> {
        turn.wait_for(i)?;
        let t = std::time::Instant::now();
        let radii: Vec<Option<f64>> = {
            let mut guard = shared.lock().unwrap_or_else(|e| e.into_inner());
            contributions.iter().map(|(n, c)| guard.0.get_mut(*n).and_then(|a| a.admit(c))).collect()
        };
        pb.inc(1);
        turn.pass(i + 1);
        let binned: Vec<(&str, f64, Vec<u64>)> = contributions.iter().zip(radii).filter_map(|((n, c), r)| Some((*n, r?, c.summary.as_ref()?.bin_at(r?)))).collect();
        let mut guard = shared.lock().unwrap_or_else(|e| e.into_inner());
        for (n, r, counts) in binned {
            if let Some(h) = guard.0.get_mut(n).and_then(|a| a.histogram.as_mut()) {
                h.add_binned(r, &counts);
            }
        }
        guard.1 += spent + t.elapsed().as_secs_f64();
        Ok(())
    };
    std::thread::scope(|scope| -> Result<()> {
        let handles: Vec<_> = (0..workers)
            .map(|k| {
                let (turn, contribute, absorb, observed, exposed) = (&turn, &contribute, &absorb, &observed, &exposed);
                let work = move || -> Result<()> {
                    let session = if exposed.is_empty() { Ok(None) } else { OrtRuntime::with_options(observed, GraphOptimizationLevel::Level3, session_threads).map(Some) };
                    // A worker without a session stops the others too: they would wait for
                    // its frames' turns.
                    let mut rt = session.inspect_err(|_| turn.abort())?;
                    for i in (k..feeds.len()).step_by(workers) {
                        let done = match rt.as_mut() {
                            Some(rt) => rt.visit_f32(&feeds[i], |outputs| contribute(i, outputs)),
                            None => Ok(contribute(i, &[])),
                        }
                        .and_then(|c| absorb(i, c));
                        if let Err(e) = done {
                            turn.abort();
                            return Err(e);
                        }
                    }
                    Ok(())
                };
                scope.spawn(move || {
                    // A worker that panics stops the others too, as one that fails does.
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)).unwrap_or_else(|_| {
                        turn.abort();
                        Err(anyhow::anyhow!("a calibration worker panicked"))
                    })
                })
            })
            .collect();
        let results: Vec<Result<()>> = handles.into_iter().map(|w| w.join().unwrap_or_else(|_| Err(anyhow::anyhow!("a calibration worker panicked")))).collect();
        // The worker that failed first says why; the others only say they stopped.
        let mut errors: Vec<anyhow::Error> = results.into_iter().filter_map(Result::err).collect();
        errors.sort_by_key(|e| e.to_string().starts_with("calibration stopped"));
        errors.into_iter().next().map_or(Ok(()), Err)
    })?;
    pb.finish_and_clear();
    let (acc, statistics_seconds) = shared.into_inner().unwrap_or_else(|e| e.into_inner());
    let n = feeds.len().max(1) as f64;
    let (mut histograms, mut channel_means) = (HashMap::new(), HashMap::new());
    for (v, a) in acc {
        if let Some(sums) = a.channel_sums {
            channel_means.insert(v.clone(), sums.into_iter().map(|s| s / n).collect());
        }
        if let Some(h) = a.histogram {
            histograms.insert(v, h);
        }
    }
    Ok(Statistics { histograms, channel_means, seconds: started.elapsed().as_secs_f64(), statistics_seconds })
}
