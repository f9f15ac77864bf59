//! Halos: what a cropped model's convolutions and poolings read past the ROI's edges.
//!
//! In the full model a convolution at the ROI's top row reads the feature rows just above it;
//! in the crop it reads zero padding, and the difference compounds layer by layer: on the
//! trained width-0.25 v5 the head logits' error falls from 0.42 in the ROI's first row to 0.06
//! sixteen rows (128 pixels) down, far past the one-stride margin `verify` leaves. A halo
//! puts an estimate of the missing rows (or columns) in place of that padding, computed in the
//! graph from the crop's own edge row: each channel at each distance from the edge is a
//! linear function of every channel of the edge (`linear`: a 1x1 convolution of the edge row;
//! `halo_rows: N` reads N rows in, an (N x 1) convolution) plus an intercept per position,
//! least-squares fitted on calibration frames to the full model's own values (with
//! `closed_loop`, from the crop's own edge rows: [`super::closed_loop`]); `mean` keeps the
//! intercept alone (the rows' average over the frames).
//! Sides where the ROI meets the frame's border keep their padding: the full model pads there
//! too, so those stay exact.
//!
//! The estimate is right on average, not frame by frame. Measured on the lower two thirds of
//! the trained models (200 held-out frames, agreement mAP@0.5:0.95 with the full model, no
//! recovery; v5 w0.25 / v8 w0.25 / v5 tiny): zero padding 0.43 / 0.91 / 0.48; `linear` from
//! the edge row, with [`super::pool`]'s correction, fitted on 64 physics-pipeline frames: 0.986
//! / 0.980 / 0.906 (fitting frames drawn with another seed: 0.985 / 0.980 / 0.894). The edge's
//! channels together say most of what the rows past it hold: the error on the fitting frames
//! is 0.16-0.21 of zero padding's. A slope per channel instead of the mix (tried, before the
//! fix that made these fits reproducible) lost 0.03 / 0.00 / 0.27 of agreement. Closed loop
//! gives 0.989 / 0.980 / 0.897.
//!
//! The halo is a Slice of the edge, a Conv, an Add and a Concat per padded value (a
//! Reshape more for a halo deeper than one row, and a Transpose for side columns): operators
//! every target runs, on rows a few pixels deep. They are not free on a CPU: 150-175 small
//! nodes on the trained models, whose crop ran at 0.93-1.01x of the full model's ORT latency
//! at 256x192 instead of 0.67x (full-size v5 at 640x480: 0.742x against 0.661x); `halo: zero`
//! keeps that speed.

use crate::ir::{infer, Graph};
use crate::onnx::attr;
use crate::onnx::edit::{add_constant, fresh_name};
use crate::onnx::proto::{GraphProto, ModelProto, NodeProto};
use crate::ridge::Moments;
use crate::scene::Roi;
use crate::tensor::{Tensor, TensorData};
use anyhow::Result;
use std::collections::BTreeMap;

#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Deserialize, serde::Serialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Mode {
    /// Zero padding, as the crop alone leaves it.
    Zero,
    /// The rows' average over the calibration frames: a constant Concat, the cheapest.
    Mean,
    /// Every channel of the edge row mixed (a 1x1 convolution) plus the average.
    #[default]
    Linear,
}

/// Ridge strength of the linear fit, relative to the edge channels' mean variance: a deep
/// map's edge has 8 positions per frame at 256x192, 512 samples on 64 frames for up to 256
/// channels, so the system needs some pull towards the mean.
const RIDGE: f64 = 1e-3;

/// The most weights one strip's mix may have (its Gram and cross moments are as large, in
/// f64): a 512-channel map's one-row halo has 262,144; past the bound (an untrusted model's
/// huge channel count or padding) the strip falls back to the mean.
pub(super) const MAX_MIX: usize = 1 << 22;

/// Sides in ONNX `pads` order: top, left, bottom, right.
const SIDES: [&str; 4] = ["top", "left", "bottom", "right"];

/// One value read with padding: the halo depth it gets on each side.
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
struct Read {
    value: String,
    halo: [usize; 4],
}

/// Where a value of the full model lies: its channels, the crop's rows and columns in it
/// (`begin`, `len` per spatial axis), and how many rows or columns exist past each side.
#[derive(Clone, Copy)]
pub(super) struct Place {
    pub channels: usize,
    pub full: [usize; 2],
    pub begin: [usize; 2],
    pub len: [usize; 2],
    outside: [usize; 4],
}

/// The calibration frames' values for one side of one value: the strip of `depth` rows (or
/// columns) past the edge, at each position `along` it, and the edge row itself.
struct Strip {
    depth: usize,
    /// Rows (or columns) of the crop the estimate reads, from its edge inwards.
    rows: usize,
    /// Range of the other axis covered: for rows, the crop's columns; for columns, the crop's
    /// rows extended by the row halos (the corners are estimated too).
    along: (usize, usize),
    /// Per frame: the edge, [C][rows][T] (row 0 the edge itself); the strip, [C][depth][T]
    /// (depth 0 next to the edge).
    edge: Vec<f32>,
    past: Vec<f32>,
}

/// The fitted estimate of one strip: `mix` on the rows read (zero for `mean`), plus
/// `intercept` [C][depth][T].
struct Fit {
    /// Rows read from the edge inwards; `mix` is [(C * depth) x (C * rows)].
    rows: usize,
    mix: Vec<f64>,
    intercept: Vec<f32>,
    /// Squared error of the estimate and of zero padding against the true rows.
    error: f64,
    zero_error: f64,
}

pub struct Report {
    pub reads: usize,
    pub values: usize,
    pub frames: usize,
    /// Per side: the halos' error against the full model's rows, relative to zero padding's,
    /// on the calibration frames (0 = exact, 1 = no better than zeros).
    pub rel_error: BTreeMap<&'static str, f64>,
}

/// The halos of one cropped model: the values its convolutions and poolings read with padding
/// past the ROI's edge, where each lies in the full model, and each strip's calibration
/// values. The strips are collected from the full model ([`Plan::observe_full`]);
/// [`Plan::take_edges`] replaces a value's edge rows with the crop's own (see
/// [`super::closed_loop`]) before [`Plan::emit`] fits and writes its halos.
pub struct Plan {
    places: BTreeMap<String, Place>,
    reads: BTreeMap<Read, Vec<usize>>,
    strips: BTreeMap<(String, usize), Strip>,
    /// Per side: squared error of the halos and of zero padding, summed over emitted strips.
    errors: BTreeMap<&'static str, (f64, f64)>,
}

impl Plan {
    /// Finds the padded reads of `cropped` (the `full` model cut to `roi` of a `frame`), each
    /// reading `rows` rows in from the edge. Only Conv and MaxPool with explicit pads get halos.
    pub fn new(cropped: &ModelProto, full: &ModelProto, roi: Roi, frame: [usize; 2], rows: usize) -> Result<Plan> {
        let fg = full.graph.as_ref().ok_or_else(|| anyhow::anyhow!("the model has no graph"))?;
        let inf = infer(&Graph::build(fg)?);
        let g = cropped.graph.as_ref().ok_or_else(|| anyhow::anyhow!("the model has no graph"))?;
        let mut places: BTreeMap<String, Place> = BTreeMap::new();
        let mut reads: BTreeMap<Read, Vec<usize>> = BTreeMap::new();
        for (i, n) in g.node.iter().enumerate() {
            if !matches!(n.op_type.as_str(), "Conv" | "MaxPool") || attr::string(n, "auto_pad", "NOTSET") != "NOTSET" {
                continue;
            }
            let Some(pads) = attr::ints(n, "pads").filter(|p| p.len() == 4 && p.iter().any(|&v| v > 0)) else { continue };
            let Some(place) = place(&inf, &n.input[0], roi, frame) else { continue };
            let halo: [usize; 4] = std::array::from_fn(|s| (pads[s].max(0) as usize).min(place.outside[s]));
            if halo.iter().all(|&h| h == 0) {
                continue;
            }
            places.insert(n.input[0].clone(), place);
            reads.entry(Read { value: n.input[0].clone(), halo }).or_default().push(i);
        }
        // The deepest halo each side of each value needs: one strip of statistics serves them all.
        let mut depth: BTreeMap<&str, [usize; 4]> = BTreeMap::new();
        for r in reads.keys() {
            let d = depth.entry(r.value.as_str()).or_default();
            for s in 0..4 {
                d[s] = d[s].max(r.halo[s]);
            }
        }
        let mut strips: BTreeMap<(String, usize), Strip> = BTreeMap::new();
        for (v, d) in &depth {
            let p = places[*v];
            for s in 0..4 {
                if d[s] == 0 {
                    continue;
                }
                let along = if s % 2 == 0 { (p.begin[1], p.begin[1] + p.len[1]) } else { (p.begin[0] - d[0], p.begin[0] + p.len[0] + d[2]) };
                let rows = rows.min(p.len[s % 2]).max(1);
                strips.insert((v.to_string(), s), Strip { depth: d[s], rows, along, edge: Vec::new(), past: Vec::new() });
            }
        }
        Ok(Plan { places, reads, strips, errors: BTreeMap::new() })
    }

    /// The full model's values the strips are collected from.
    pub fn values(&self) -> impl Iterator<Item = &String> {
        self.places.keys()
    }

    /// Appends one frame's strips of `value` from `data`, its value in the full model
    /// ([1, C, H, W]); call it for each of [`Plan::values`], frame by frame.
    pub fn observe_full(&mut self, value: &str, data: &[f32]) {
        let Some(p) = self.places.get(value) else { return };
        if data.len() != p.channels * p.full[0] * p.full[1] {
            return;
        }
        for s in 0..4 {
            if let Some(strip) = self.strips.get_mut(&(value.to_string(), s)) {
                accumulate(strip, s, p, data);
            }
        }
    }

    /// Each value that gets a halo, with the indices of the nodes that read it padded.
    pub fn readers(&self) -> BTreeMap<&str, Vec<usize>> {
        let mut out: BTreeMap<&str, Vec<usize>> = BTreeMap::new();
        for (r, consumers) in &self.reads {
            out.entry(r.value.as_str()).or_default().extend(consumers);
        }
        out
    }

    /// Replaces frame `f`'s edge rows of `value`'s strips with `data`, the value as the
    /// cropped model computes it ([1, C, h, w] over the crop). A side column's strip also
    /// covers the row halos' corners, which the crop does not hold: those keep the full
    /// model's values.
    pub fn take_edges(&mut self, value: &str, f: usize, data: &[f32]) {
        let Some(p) = self.places.get(value).copied() else { return };
        let [h, w] = p.len;
        if data.len() != p.channels * h * w {
            return;
        }
        for s in 0..4 {
            let Some(strip) = self.strips.get_mut(&(value.to_string(), s)) else { continue };
            let t = strip.along.1 - strip.along.0;
            let block = p.channels * strip.rows * t;
            if strip.edge.len() < (f + 1) * block {
                continue;
            }
            for c in 0..p.channels {
                for j in 0..strip.rows {
                    for (x, a) in (strip.along.0..strip.along.1).enumerate() {
                        let (y, col) = match s {
                            0 => (j, a.wrapping_sub(p.begin[1])),
                            2 => (h - 1 - j, a.wrapping_sub(p.begin[1])),
                            1 => (a.wrapping_sub(p.begin[0]), j),
                            _ => (a.wrapping_sub(p.begin[0]), w - 1 - j),
                        };
                        if y < h && col < w {
                            strip.edge[f * block + (c * strip.rows + j) * t + x] = data[(c * h + y) * w + col];
                        }
                    }
                }
            }
        }
    }

    /// Fits `value`'s strips and writes its halos into `g`: each padded read of it reads the
    /// halo'd value instead, with its padding reduced by the halo. Nodes are only appended, so
    /// the indices [`Plan::readers`] gave stay valid; the caller sorts the graph at the end.
    pub fn emit(&mut self, g: &mut GraphProto, value: &str, mode: Mode) {
        let mut fits: BTreeMap<(String, usize), Fit> = BTreeMap::new();
        for (key, strip) in self.strips.range((value.to_string(), 0)..=(value.to_string(), 3)) {
            let f = fit(strip, self.places[&key.0].channels, mode);
            let e = self.errors.entry(SIDES[key.1]).or_default();
            e.0 += f.error;
            e.1 += f.zero_error;
            fits.insert(key.clone(), f);
        }
        for (read, consumers) in self.reads.iter().filter(|(r, _)| r.value == value) {
            let p = self.places[&read.value];
            let padded = emit(g, read, &p, &self.strips, &fits);
            for &i in consumers {
                let n = &mut g.node[i];
                n.input[0] = padded.clone();
                let pads = attr::ints(n, "pads").expect("checked in Plan::new");
                let left: Vec<i64> = pads.iter().zip(read.halo).map(|(&p, h)| p - h as i64).collect();
                n.attribute.retain(|a| a.name != "pads");
                n.attribute.push(attr::make_ints("pads", left));
            }
        }
    }

    /// The report, for halos fitted on `frames` calibration frames.
    pub fn report(&self, frames: usize) -> Report {
        Report {
            reads: self.reads.values().map(Vec::len).sum(),
            values: self.places.len(),
            frames,
            rel_error: self.errors.iter().map(|(s, (a, b))| (*s, (a / b.max(1e-300)).sqrt())).collect(),
        }
    }
}

/// Where `value` lies in the full model, when its stride divides the ROI.
pub(super) fn place(inf: &crate::ir::Inferred, value: &str, roi: Roi, frame: [usize; 2]) -> Option<Place> {
    let s = inf.shape(value)?;
    if s.len() != 4 || s[0] != 1 || s[2] == 0 || s[3] == 0 || !frame[0].is_multiple_of(s[2]) || !frame[1].is_multiple_of(s[3]) {
        return None;
    }
    let (sy, sx) = (frame[0] / s[2], frame[1] / s[3]);
    if !roi.y.is_multiple_of(sy) || !roi.h.is_multiple_of(sy) || !roi.x.is_multiple_of(sx) || !roi.w.is_multiple_of(sx) {
        return None;
    }
    let begin = [roi.y / sy, roi.x / sx];
    let len = [roi.h / sy, roi.w / sx];
    Some(Place { channels: s[1], full: [s[2], s[3]], begin, len, outside: [begin[0], begin[1], s[2] - begin[0] - len[0], s[3] - begin[1] - len[1]] })
}

/// Appends one frame's edge and strip (rows or columns past side `s`).
fn accumulate(strip: &mut Strip, s: usize, p: &Place, data: &[f32]) {
    let (h, w) = (p.full[0], p.full[1]);
    let rows = s.is_multiple_of(2);
    let at = |c: usize, k: usize, a: usize| if rows { data[(c * h + k) * w + a] } else { data[(c * h + a) * w + k] };
    // The edge's index on the strip's axis, and the index `j` steps past it.
    let edge = match s {
        0 | 1 => p.begin[s],
        _ => p.begin[s - 2] + p.len[s - 2] - 1,
    };
    let past = |j: usize| if s < 2 { edge - 1 - j } else { edge + 1 + j };
    let along = strip.along.0..strip.along.1;
    let inward = |j: usize| if s < 2 { edge + j } else { edge - j };
    for c in 0..p.channels {
        for j in 0..strip.rows {
            strip.edge.extend(along.clone().map(|a| at(c, inward(j), a)));
        }
        for j in 0..strip.depth {
            strip.past.extend(along.clone().map(|a| at(c, past(j), a)));
        }
    }
}

/// The least-squares estimate of a strip from the rows next to its edge: each (channel, depth)
/// of the strip a linear function of every channel of the rows read (`Linear`) or a constant
/// (`Mean`), with an intercept per position: the fit runs on values centred per position, so
/// a position's average (a column under the vignetting, a gate map's slope) is the
/// intercept's, and the mix carries only what varies from frame to frame.
fn fit(strip: &Strip, channels: usize, mode: Mode) -> Fit {
    let t = strip.along.1 - strip.along.0;
    // Features: every channel of every row read, `ch * rows + j`.
    let (c, m) = (channels * strip.rows, channels * strip.depth);
    let frames = strip.edge.len() / (c * t).max(1);
    let n = frames.max(1) as f64;
    let edge = |f: usize, ft: usize, x: usize| strip.edge[(f * c + ft) * t + x] as f64;
    let past = |f: usize, k: usize, x: usize| strip.past[(f * m + k) * t + x] as f64;
    let edge_mean: Vec<f64> = (0..c * t).map(|i| (0..frames).map(|f| edge(f, i / t, i % t)).sum::<f64>() / n).collect();
    let past_mean: Vec<f64> = (0..m * t).map(|i| (0..frames).map(|f| past(f, i / t, i % t)).sum::<f64>() / n).collect();
    let (mut rows, mut mix) = (1, vec![0.0; m * channels]);
    if mode == Mode::Linear && frames >= 2 && m * c <= MAX_MIX {
        let mut moments = Moments::new(c, m);
        let xs: Vec<Vec<f64>> = (0..c).map(|ft| (0..frames * t).map(|i| edge(i / t, ft, i % t) - edge_mean[ft * t + i % t]).collect()).collect();
        let ts: Vec<Vec<f64>> = (0..m).map(|k| (0..frames * t).map(|i| past(i / t, k, i % t) - past_mean[k * t + i % t]).collect()).collect();
        moments.add_columns(&xs, &ts);
        if let Some((mm, _)) = moments.solve(RIDGE, None) {
            (rows, mix) = (strip.rows, mm);
        }
    }
    // Without a mix, only the first row's (zero) weights remain.
    let d = channels * rows;
    let mut intercept = vec![0f32; m * t];
    for k in 0..m {
        for x in 0..t {
            let b = past_mean[k * t + x] - (0..d).map(|ft| mix[k * d + ft] * edge_mean[ft * t + x]).sum::<f64>();
            intercept[k * t + x] = b as f32;
        }
    }
    let (mut error, mut zero_error) = (0.0, 0.0);
    for f in 0..frames {
        for k in 0..m {
            for x in 0..t {
                let y = past(f, k, x);
                let est = intercept[k * t + x] as f64 + (0..d).map(|ft| mix[k * d + ft] * edge(f, ft, x)).sum::<f64>();
                error += (y - est) * (y - est);
                zero_error += y * y;
            }
        }
    }
    Fit { rows, mix, intercept, error, zero_error }
}

/// Writes the nodes that pad `read.value` with its halos (rows, then columns) and returns the
/// padded value's name.
fn emit(g: &mut GraphProto, read: &Read, p: &Place, strips: &BTreeMap<(String, usize), Strip>, fits: &BTreeMap<(String, usize), Fit>) -> String {
    let mut cur = read.value.clone();
    // Rows: [1, C, h, w] -> [1, C, top + h + bottom, w]; columns after, over the new rows.
    let mut extent = p.len;
    for (axis, before, after) in [(2usize, 0usize, 2usize), (3, 1, 3)] {
        if read.halo[before] == 0 && read.halo[after] == 0 {
            continue;
        }
        let mut parts = Vec::new();
        for s in [before, after] {
            let d = read.halo[s];
            if d == 0 {
                continue;
            }
            let key = (read.value.clone(), s);
            let (strip, f) = (&strips[&key], &fits[&key]);
            // The part of the strip's fitted range this read covers (columns: its row halos).
            let n_along = strip.along.1 - strip.along.0;
            let skip = if axis == 3 { (p.begin[0] - read.halo[0]) - strip.along.0 } else { 0 };
            let len = if axis == 3 { extent[0] } else { extent[1] };
            // Order along the axis: a side before the crop lists its rows farthest first.
            let depth_at = |r: usize| if s == before { d - 1 - r } else { r };
            let mut shape = vec![1, p.channels, 0, 0];
            shape[axis] = d;
            shape[5 - axis] = len;
            let c_in = p.channels;
            let mut b = vec![0f32; c_in * d * len];
            // The mix is a convolution over the rows read, [C * d, C, rows, 1] ([.., 1, rows] for
            // columns): output channel c * d + r is row r of channel c; kernel tap `at` reads
            // the row `inward(at)` steps in from the edge (the slice lists rows in index order).
            let reads = f.rows;
            let inward = |at: usize| if s == before { at } else { reads - 1 - at };
            let mut w = vec![0f32; c_in * d * c_in * reads];
            for c in 0..c_in {
                for r in 0..d {
                    let k = c * strip.depth + depth_at(r);
                    for ch in 0..c_in {
                        for at in 0..reads {
                            w[((c * d + r) * c_in + ch) * reads + at] = f.mix[(k * c_in + ch) * reads + inward(at)] as f32;
                        }
                    }
                    for t in 0..len {
                        let at = if axis == 2 { (c * d + r) * len + t } else { (c * len + t) * d + r };
                        b[at] = f.intercept[k * n_along + skip + t];
                    }
                }
            }
            let tag = format!("{}_halo_{}", read.value, SIDES[s]);
            let rows = constant(g, &format!("{tag}_intercept"), shape.clone(), b);
            // A fit with no mix (`mean`, or past MAX_MIX) is its constant rows alone.
            let part = if f.mix.iter().any(|&v| v != 0.0) {
                let first = if s == before { 0 } else { (extent[axis - 2] - reads) as i64 };
                let starts = constant_i64s(g, &format!("{tag}_start"), vec![first]);
                let ends = constant_i64s(g, &format!("{tag}_end"), vec![first + reads as i64]);
                let axes = constant_i64s(g, &format!("{tag}_axis"), vec![axis as i64]);
                let kernel = if axis == 2 { [reads, 1] } else { [1, reads] };
                let weight = constant(g, &format!("{tag}_mix"), vec![c_in * d, c_in, kernel[0], kernel[1]], w);
                let edge = node(g, "Slice", &format!("{tag}_edge"), vec![cur.clone(), starts, ends, axes], vec![]);
                let mixed = node(g, "Conv", &format!("{tag}_mixed"), vec![edge, weight], vec![attr::make_ints("kernel_shape", kernel.iter().map(|&k| k as i64).collect())]);
                // [N, C * d, 1, len] or [N, C * d, len, 1] -> [N, C, d, len] (-> [N, C, len, d]);
                // one row deep (a 3x3 kernel's halo) it already is: a node costs ORT ~10 us.
                let mut est = mixed;
                if d > 1 {
                    // Batch 0: the input's own (1 here; the recovery worker's batches elsewhere).
                    let target = constant_i64s(g, &format!("{tag}_shape"), vec![0, c_in as i64, d as i64, len as i64]);
                    est = node(g, "Reshape", &format!("{tag}_rows"), vec![est, target], vec![]);
                    if axis == 3 {
                        est = node(g, "Transpose", &format!("{tag}_columns"), vec![est], vec![attr::make_ints("perm", vec![0, 1, 3, 2])]);
                    }
                }
                node(g, "Add", &tag, vec![est, rows], vec![])
            } else {
                rows
            };
            parts.push((s == before, part));
        }
        let mut inputs: Vec<String> = parts.iter().filter(|x| x.0).map(|x| x.1.clone()).collect();
        inputs.push(cur.clone());
        inputs.extend(parts.iter().filter(|x| !x.0).map(|x| x.1.clone()));
        let halo = read.halo;
        cur = node(g, "Concat", &format!("{}_halo_{}", read.value, halo.iter().map(|h| h.to_string()).collect::<Vec<_>>().join("_")), inputs, vec![attr::make_int("axis", axis as i64)]);
        extent[axis - 2] += read.halo[before] + read.halo[after];
    }
    cur
}

pub(super) fn constant(g: &mut GraphProto, base: &str, shape: Vec<usize>, v: Vec<f32>) -> String {
    add_constant(g, base, &Tensor::f32(shape, v))
}

fn constant_i64s(g: &mut GraphProto, base: &str, v: Vec<i64>) -> String {
    add_constant(g, base, &Tensor::new(vec![v.len()], TensorData::I64(v)))
}

/// Appends a node with a fresh output name (its node name is the same) and returns the output.
pub(super) fn node(g: &mut GraphProto, op: &str, base: &str, input: Vec<String>, attribute: Vec<crate::onnx::proto::AttributeProto>) -> String {
    let out = fresh_name(g, base);
    g.node.push(NodeProto { name: out.clone(), op_type: op.into(), input, output: vec![out.clone()], attribute, ..Default::default() });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Rows that are an exact linear function of the two rows read (plus a per-position
    /// offset) are fitted exactly, with the mix and the intercept where `emit` reads them.
    #[test]
    fn linear_fit_recovers_an_exact_relation() {
        let (c, rows, depth, t, frames) = (3usize, 2usize, 2usize, 5usize, 60usize);
        let f = c * rows;
        let mix = |k: usize, ft: usize| ((k * 7 + ft * 3) % 5) as f64 * 0.25 - 0.5;
        let offset = |k: usize, x: usize| (k + x) as f64 * 0.1;
        let mut rng = crate::optics::rng::Rng::new(7);
        let mut strip = Strip { depth, rows, along: (2, 2 + t), edge: Vec::new(), past: Vec::new() };
        for _ in 0..frames {
            let e: Vec<f64> = (0..f * t).map(|_| rng.normal()).collect();
            strip.edge.extend(e.iter().map(|&v| v as f32));
            for k in 0..c * depth {
                for x in 0..t {
                    let v = offset(k, x) + (0..f).map(|ft| mix(k, ft) * e[ft * t + x]).sum::<f64>();
                    strip.past.push(v as f32);
                }
            }
        }
        let fitted = fit(&strip, c, Mode::Linear);
        assert_eq!(fitted.rows, rows);
        assert!(fitted.error < 1e-4 * fitted.zero_error, "error {} of {}", fitted.error, fitted.zero_error);
        for k in 0..c * depth {
            for ft in 0..f {
                assert!((fitted.mix[k * f + ft] - mix(k, ft)).abs() < 1e-3, "mix[{k}][{ft}] = {}", fitted.mix[k * f + ft]);
            }
            for x in 0..t {
                assert!((fitted.intercept[k * t + x] as f64 - offset(k, x)).abs() < 1e-3);
            }
        }
        let mean = fit(&strip, c, Mode::Mean);
        assert!(mean.mix.iter().all(|&m| m == 0.0) && mean.error > 100.0 * fitted.error);
    }
}
