//! Latency measured interleaved: reference and candidate alternate within one loop, so
//! machine noise (frequency, other load) hits both alike and their ratio stays meaningful.

use crate::runtime::Runtime;
use crate::tensor::Tensor;
use anyhow::Result;
use serde::Serialize;
use std::time::Instant;

/// Warm-up runs per model before timing: first runs pay for allocation and kernel selection.
const WARMUP: usize = 2;

/// Pause before each timed run. ONNX Runtime's intra-op threads and tract's rayon pool keep
/// spinning after a run returns, and take cores from whatever runs next. Measured on the
/// full-size v5 at 640x480, one model as both reference and candidate on 2 cores (the
/// candidate follows the reference in two rounds of three): without a pause the candidate
/// timed 271 against 247 ms; with 20 ms, 254 against 243; with 60 ms, equal (ratio 0.996-0.997
/// in three runs), and 150 ms measured no better.
const SETTLE: std::time::Duration = std::time::Duration::from_millis(60);

#[derive(Debug, Clone, Serialize)]
pub struct Latency {
    pub name: String,
    pub median_ms: f64,
    pub min_ms: f64,
    pub runs: usize,
}

/// Times each of `models` `runs` times, rotating which goes first each round.
pub fn interleaved(models: &mut [(String, &mut dyn Runtime, Vec<(String, Tensor)>)], runs: usize) -> Result<Vec<Latency>> {
    for (_, rt, inputs) in models.iter_mut() {
        for _ in 0..WARMUP {
            rt.run(inputs)?;
        }
    }
    let n = models.len();
    let mut times = vec![Vec::with_capacity(runs); n];
    for r in 0..runs {
        for k in 0..n {
            let i = (r + k) % n;
            let (_, rt, inputs) = &mut models[i];
            std::thread::sleep(SETTLE);
            let t = Instant::now();
            rt.run(inputs)?;
            times[i].push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok(models
        .iter()
        .zip(times)
        .map(|((name, _, _), t)| {
            let t = crate::metrics::order::sorted(t);
            Latency { name: name.clone(), median_ms: crate::metrics::order::quantile(&t, 0.5), min_ms: t[0], runs }
        })
        .collect())
}
