//! The order a crop's estimates are fitted in: each from what the crop itself computes.
//!
//! A halo maps the crop's edge rows to the full model's rows past the edge, and a pool's
//! correction maps the ROI's channel means to the frame's. Fitted on the full model's own
//! edge rows and ROI means (open loop), each estimate is right for inputs the crop never
//! sees: a cropped layer's edge rows already carry the error of every estimate above it, and
//! the errors compound through the depth of the network. Fitted closed loop, each estimate
//! reads the crop's own values with every estimate upstream of it in place; its targets stay
//! the full model's. A value's *wave* is the number of halo'd or pooled reads on the longest
//! path to it, so the estimates of one wave do not feed each other and one run of the crop
//! per wave gives the inputs of all of its fits (a few dozen runs of the cropped model).
//!
//! Measured on the lower two thirds of the trained models (200 held-out frames of
//! `scripts/eval-set`; v5 w0.25 / v8 w0.25 / v5 tiny), open loop against closed: the classes'
//! rel L2 inside the ROI 0.114 / 0.056 / 0.155 against 0.109 / 0.059 / 0.151, agreement
//! mAP@0.5:0.95 0.986 / 0.980 / 0.906 against 0.989 / 0.980 / 0.897; on the v5's box ROI
//! `{x: 64, y: 64, w: 128, h: 96}` (halos on four sides, 19 reference boxes) 0.963 against
//! 0.894, boxes' rel L2 0.054 against 0.060. Even at best, within what a few detections near
//! the score threshold decide. It costs a run of the crop per wave (38 waves on the w0.25
//! models), so it is opt-in (`crop-roi: {closed_loop: true}`). It is the better start for
//! training the estimates end to end (`recover: {train: estimates}`): the tiny agreed 0.931
//! trained from closed loop, 0.913 from open loop, 4 minutes each.

use super::halo::{self, Mode, Plan};
use super::pool::{PoolReport, Pools};
use super::Roi;
use crate::ir::Graph;
use crate::onnx::edit::expose_outputs;
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::{GraphProto, ModelProto};
use crate::runtime::ort_runtime::OrtRuntime;
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};
use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet};

pub struct Fitted {
    pub halos: halo::Report,
    pub pools: Vec<PoolReport>,
    /// Runs of the crop that fitted them (0 for open loop).
    pub waves: usize,
}

/// What one wave fits: halo'd values and pools (by index into [`Pools::nodes`]).
#[derive(Default)]
struct Wave {
    values: Vec<String>,
    pools: Vec<usize>,
}

/// Adds the halos (and with `pools`, the pool corrections) to `cropped`, the `full` model cut
/// to `roi` of a `frame`, fitted on `frames` (feeds of the full model); `closed`: each from
/// the crop's own values, wave by wave; otherwise all from the full model's.
#[allow(clippy::too_many_arguments)]
pub fn fit(cropped: &mut ModelProto, full: &ModelProto, roi: Roi, frame: [usize; 2], frames: &[Vec<(String, Tensor)>], mode: Mode, rows: usize, pools: bool, closed: bool, threads: usize) -> Result<Fitted> {
    let mut plan = Plan::new(cropped, full, roi, frame, rows)?;
    let mut means = if pools && mode != Mode::Zero { Pools::new(cropped, full, roi, frame)? } else { Pools::none() };
    // One run of the full model gives every strip's and pool's values.
    let names: BTreeSet<String> = plan.values().cloned().chain(means.nodes.iter().map(|n| n.1.clone())).collect();
    if !names.is_empty() {
        let names: Vec<String> = names.into_iter().collect();
        let mut rt = OrtRuntime::with_options(&expose_outputs(full, &names), ort::session::builder::GraphOptimizationLevel::Level1, threads)?;
        for feed in frames {
            rt.visit_f32(feed, |seen| {
                for (name, data) in seen {
                    plan.observe_full(name, data);
                    means.observe_full(name, data);
                }
            })?;
        }
    }
    let g = cropped.graph.as_ref().ok_or_else(|| anyhow!("the model has no graph"))?;
    let waves = waves(g, &plan.readers(), &means.nodes)?;
    if waves.is_empty() {
        return Ok(Fitted { halos: plan.report(frames.len()), pools: Vec::new(), waves: 0 });
    }
    let crops: Vec<Vec<(String, Tensor)>> = if closed { frames.iter().map(|f| crop_feed(f, roi, frame)).collect::<Result<_>>()? } else { Vec::new() };
    let mut reports = Vec::new();
    for wave in waves.values() {
        if closed {
            let mut names = wave.values.clone();
            names.extend(wave.pools.iter().map(|&k| means.nodes[k].1.clone()));
            let mut rt = OrtRuntime::with_options(&exposing(cropped, &names)?, ort::session::builder::GraphOptimizationLevel::Level1, threads)?;
            for (f, feed) in crops.iter().enumerate() {
                rt.visit_f32(feed, |seen| {
                    for (name, data) in seen {
                        plan.take_edges(name, f, data);
                        means.take_means(name, f, data);
                    }
                })?;
            }
        }
        let g = cropped.graph.as_mut().ok_or_else(|| anyhow!("the model has no graph"))?;
        for v in &wave.values {
            plan.emit(g, v, mode);
        }
        reports.extend(wave.pools.iter().filter_map(|&k| means.emit(g, k, mode)));
    }
    settle(cropped.graph.as_mut().ok_or_else(|| anyhow!("the model has no graph"))?)?;
    Ok(Fitted { halos: plan.report(frames.len()), pools: reports, waves: if closed { waves.len() } else { 0 } })
}

/// Groups the halo'd values and the pools by wave: the most halo'd or pooled reads on any path
/// from the inputs to the value read. `readers`: each halo'd value and the nodes that read it
/// padded; `pools`: each pool's node and input.
fn waves(g: &GraphProto, readers: &BTreeMap<&str, Vec<usize>>, pools: &[(usize, String)]) -> Result<BTreeMap<usize, Wave>> {
    // Nodes whose first input is read through an estimate.
    let estimated: HashSet<usize> = readers.values().flatten().copied().chain(pools.iter().map(|n| n.0)).collect();
    let mut depth: HashMap<&str, usize> = HashMap::new();
    for i in Graph::build(g)?.order {
        let n = &g.node[i];
        let d = n.input.iter().enumerate().map(|(slot, v)| depth.get(v.as_str()).copied().unwrap_or(0) + usize::from(slot == 0 && estimated.contains(&i))).max().unwrap_or(0);
        for o in &n.output {
            depth.insert(o.as_str(), d);
        }
    }
    let at = |v: &str| depth.get(v).copied().unwrap_or(0);
    let mut waves: BTreeMap<usize, Wave> = BTreeMap::new();
    for v in readers.keys() {
        waves.entry(at(v)).or_default().values.push(v.to_string());
    }
    for (k, (_, v)) in pools.iter().enumerate() {
        waves.entry(at(v)).or_default().pools.push(k);
    }
    Ok(waves)
}

/// The cropped model as it stands (estimates of earlier waves in place), computing only `names`.
fn exposing(cropped: &ModelProto, names: &[String]) -> Result<ModelProto> {
    let mut m = cropped.clone();
    let g = m.graph.as_mut().ok_or_else(|| anyhow!("the model has no graph"))?;
    settle(g)?;
    g.output = names.iter().map(|n| g.value_info.iter().find(|v| &v.name == n).cloned().unwrap_or_else(|| crate::onnx::proto::ValueInfoProto { name: n.clone(), ..Default::default() })).collect();
    crate::ir::rewrite::dce::eliminate(g)?;
    Ok(m)
}

/// Puts appended nodes in order and their value_info afresh (no stale shape from before).
fn settle(g: &mut GraphProto) -> Result<()> {
    sort_topologically(g)?;
    g.value_info.clear();
    crate::ir::rewrite::value_info::write_value_info(g)?;
    Ok(())
}

/// A feed of full frames, cropped where an input is a `frame`-sized image.
fn crop_feed(feed: &[(String, Tensor)], roi: Roi, frame: [usize; 2]) -> Result<Vec<(String, Tensor)>> {
    feed.iter()
        .map(|(n, t)| {
            let image = t.shape.len() == 4 && t.shape[2..] == frame[..];
            let t = if image { roi.crop(t).ok_or_else(|| anyhow!("input {n} of shape {:?} does not hold the ROI", t.shape))? } else { t.clone() };
            Ok((n.clone(), t))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::onnx::proto::NodeProto;

    fn node(op: &str, input: &[&str], output: &str) -> NodeProto {
        NodeProto { op_type: op.into(), input: input.iter().map(|s| s.to_string()).collect(), output: vec![output.into()], ..Default::default() }
    }

    /// A value read through a halo, a pool's correction, or both on the way, comes a wave
    /// later than what it depends on; an unpadded read adds nothing.
    #[test]
    fn each_estimate_waits_for_those_upstream() {
        let g = GraphProto {
            node: vec![
                node("Conv", &["x", "w"], "a"),
                node("Relu", &["a"], "b"),
                node("Conv", &["b", "w"], "c"),
                node("GlobalAveragePool", &["c"], "d"),
                node("Mul", &["c", "d"], "e"),
                node("Conv", &["e", "w"], "f"),
                node("Conv", &["x", "w"], "g"),
                node("Conv", &["g", "w"], "h"),
            ],
            input: ["x", "w"].map(|n| crate::onnx::proto::ValueInfoProto { name: n.into(), ..Default::default() }).to_vec(),
            ..Default::default()
        };
        let readers: BTreeMap<&str, Vec<usize>> = [("x", vec![0]), ("b", vec![2]), ("e", vec![5]), ("g", vec![7])].into_iter().collect();
        let waves = waves(&g, &readers, &[(3, "c".to_string())]).unwrap();
        let at = |w: usize| (waves[&w].values.clone(), waves[&w].pools.clone());
        // "g" is read by an unpadded convolution of "x" (node 6): no halo between them.
        assert_eq!(at(0), (vec!["g".to_string(), "x".to_string()], vec![]));
        assert_eq!(at(1), (vec!["b".to_string()], vec![]));
        assert_eq!(at(2), (vec![], vec![0]));
        assert_eq!(at(3), (vec!["e".to_string()], vec![]));
        assert_eq!(waves.len(), 4);
    }
}
