//! Latency measured interleaved: reference and candidate alternate within one loop, so
//! machine noise (frequency, other load) hits both alike and their ratio stays meaningful.

use crate::runtime::Runtime;
use crate::tensor::Tensor;
use anyhow::Result;
use serde::Serialize;
use std::time::Instant;

/// Warm-up runs per model before timing: first runs pay for allocation and kernel selection.
const WARMUP: usize = 2;

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
            let t = Instant::now();
            rt.run(inputs)?;
            times[i].push(t.elapsed().as_secs_f64() * 1e3);
        }
    }
    Ok(models
        .iter()
        .zip(times)
        .map(|((name, _, _), mut t)| {
            t.sort_by(f64::total_cmp);
            Latency { name: name.clone(), median_ms: t[t.len() / 2], min_ms: t[0], runs }
        })
        .collect())
}
