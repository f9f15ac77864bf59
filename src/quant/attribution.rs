//! Where quantization error comes from, like RKNN's accuracy_analysis: for every quantized
//! value, its error against float both accumulated along the quantized graph and for its
//! layer alone (float inputs quantized once, that layer's weights quantized).
//!
//! "Alone" errors come from one run of a single model: the float graph plus, beside every
//! quantized node, a clone reading fake-quantized copies of its float inputs.

use crate::scene::compare::SceneView;
use super::params::{quantize_weights, ActivationType, QParams};
use super::plan::Plan;
use super::qdq::add_qdq;
use crate::analysis::head;
use crate::detect::decode::channel_groups;
use crate::ir::{infer, Graph};
use crate::metrics::box_error::BoxErrorSums;
use crate::metrics::tensor_error::{ErrorSums, TensorError};
use crate::onnx::edit::{expose_outputs, fresh_name, set_initializer};
use crate::ir::rewrite::topo::sort_topologically;
use crate::onnx::proto::ModelProto;
use crate::onnx::tensor_proto::{from_tensor, to_tensor};
use crate::runtime::ort_runtime::OrtRuntime;
use crate::runtime::Runtime;
use crate::tensor::Tensor;
use anyhow::{anyhow, Result};
use ort::session::builder::GraphOptimizationLevel;
use std::collections::{BTreeMap, HashMap};

pub type Feeds = [Vec<(String, Tensor)>];

#[derive(Clone, Debug, serde::Serialize)]
pub struct LayerError {
    pub node: String,
    pub op: String,
    pub value: String,
    /// This layer alone: float inputs quantized, its own weights and output quantized.
    pub alone: TensorError,
    /// The value in the quantized model against float (errors of all earlier layers included).
    pub accumulated: Option<TensorError>,
}

pub struct AloneAnalysis {
    pub layers: Vec<LayerError>,
    pub node_of_value: HashMap<String, usize>,
}

/// Runs the float model with a fake-quantized clone of every quantized node beside it.
pub fn alone(model: &ModelProto, plan: &Plan, params: &HashMap<String, QParams>, ty: ActivationType, weight_bits: u32, feeds: &Feeds, threads: usize) -> Result<AloneAnalysis> {
    let src = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let graph = Graph::build(src)?;
    let mut g = src.clone();
    let param = |v: &str| params.get(plan.root(v)).copied();
    let mut fake_inputs: HashMap<String, String> = HashMap::new();
    let mut pairs: Vec<(usize, String, String)> = Vec::new(); // node, float value, clone's value
    // A value fused into a Relu has no quantized form: the Relu's clone reads the producer's
    // clone, and the pair (the Relu's output) is reported as the producer's layer.
    let mut fused_clones: HashMap<String, (usize, String)> = HashMap::new();
    for &i in &plan.quantized {
        let mut n = src.node[i].clone();
        let mut layer = i;
        for s in Plan::activation_slots(&graph, i) {
            let v = n.input[s].clone();
            if let Some((producer, clone)) = fused_clones.get(&v) {
                n.input[s] = clone.clone();
                layer = *producer;
                continue;
            }
            let Some(p) = param(&v).or_else(|| constant_params(&graph, &v, ty)) else { continue };
            let fq = match fake_inputs.get(&v) {
                Some(f) => f.clone(),
                None => {
                    let f = add_qdq(&mut g, &v, &p, ty);
                    fake_inputs.insert(v.clone(), f.clone());
                    f
                }
            };
            n.input[s] = fq;
        }
        if n.op_type == "Conv" {
            let w = to_tensor(graph.initializers[n.input[1].as_str()])?;
            let q = quantize_weights(w.as_f32().expect("planned"), w.shape[0], weight_bits);
            let per = w.len() / w.shape[0].max(1);
            let deq: Vec<f32> = q.values.iter().enumerate().map(|(k, &x)| (x as f64 * q.scales[k / per.max(1)]) as f32).collect();
            let name = fresh_name(&g, &format!("{}_fake_quantized", n.input[1]));
            set_initializer(&mut g, from_tensor(&name, &Tensor::f32(w.shape.clone(), deq)));
            n.input[1] = name;
        }
        for o in n.output.iter_mut().filter(|o| !o.is_empty()) {
            let alone = fresh_name(&g, &format!("{o}_alone"));
            if plan.fused_relu.contains_key(o.as_str()) {
                fused_clones.insert(o.clone(), (i, alone.clone()));
            } else {
                pairs.push((layer, o.clone(), alone.clone()));
            }
            *o = alone;
        }
        n.name = format!("{}_alone", n.name);
        g.node.push(n);
    }
    sort_topologically(&mut g)?;
    let mut m = model.clone();
    m.graph = Some(g);
    let exposed: Vec<String> = pairs.iter().flat_map(|(_, a, b)| [a.clone(), b.clone()]).collect();
    let mut rt = OrtRuntime::with_options(&expose_outputs(&m, &exposed), GraphOptimizationLevel::Level1, threads)?;

    let mut sums: Vec<ErrorSums> = vec![ErrorSums::default(); pairs.len()];
    for f in feeds {
        let out: HashMap<String, Tensor> = rt.run(f)?.into_iter().collect();
        for (k, (i, v, a)) in pairs.iter().enumerate() {
            let (Some(fv), Some(av)) = (out.get(v).and_then(|t| t.as_f32()), out.get(a).and_then(|t| t.as_f32())) else { continue };
            let output_q = (!plan.float_output.contains(i)).then(|| param(v)).flatten();
            let fake = |x: f32| output_q.map_or(x as f64, |p| p.fake_quant(x as f64));
            sums[k].add(fv.iter().map(|&x| x as f64), av.iter().map(|&x| fake(x)));
        }
    }
    let layers = pairs
        .iter()
        .zip(&sums)
        .map(|((i, v, _), s)| LayerError { node: src.node[*i].name.clone(), op: src.node[*i].op_type.clone(), value: v.clone(), alone: s.finish(), accumulated: None })
        .collect();
    let node_of_value = pairs.iter().map(|(i, v, _)| (v.clone(), *i)).collect();
    Ok(AloneAnalysis { layers, node_of_value })
}

/// Per-tensor parameters of a constant operand, as emission gives it.
fn constant_params(g: &Graph, name: &str, ty: ActivationType) -> Option<QParams> {
    let t = to_tensor(g.initializers.get(name)?).ok()?;
    Some(QParams::covering(t.as_f32()?, ty))
}

/// Error of every quantized value in `quantized` (named by `dequantized`) against `float`.
pub fn accumulated(float: &ModelProto, quantized: &ModelProto, dequantized: &BTreeMap<String, String>, feeds: &Feeds, threads: usize) -> Result<HashMap<String, TensorError>> {
    let (names, dq): (Vec<String>, Vec<String>) = dequantized.iter().map(|(a, b)| (a.clone(), b.clone())).unzip();
    let mut f = OrtRuntime::with_options(&expose_outputs(float, &names), GraphOptimizationLevel::Level1, threads)?;
    let mut q = OrtRuntime::with_options(&expose_outputs(quantized, &dq), GraphOptimizationLevel::Level1, threads)?;
    let mut sums = vec![ErrorSums::default(); names.len()];
    for feed in feeds {
        let fo: HashMap<String, Tensor> = f.run(feed)?.into_iter().chain(feed.iter().cloned()).collect();
        let qo: HashMap<String, Tensor> = q.run(feed)?.into_iter().collect();
        for (k, (a, b)) in names.iter().zip(&dq).enumerate() {
            if let (Some(x), Some(y)) = (fo.get(a).and_then(|t| t.as_f32()), qo.get(b).and_then(|t| t.as_f32())) {
                sums[k].add(x.iter().map(|&v| v as f64), y.iter().map(|&v| v as f64));
            }
        }
    }
    Ok(names.into_iter().zip(sums.iter().map(|s| s.finish())).collect())
}

/// One output (or one channel group of the decoded detection output: boxes, objectness,
/// classes) and its error.
#[derive(Clone, Debug, serde::Serialize)]
pub struct OutputError {
    pub output: String,
    pub group: Option<&'static str>,
    pub error: TensorError,
}

/// Errors of `candidate`'s outputs against `reference`'s, split by channel group where the
/// output is a decoded detection tensor, so that scores are judged apart from coordinates.
/// With `scene`, the candidate is scene-specialized: it sees the crop of each frame and its
/// outputs are compared with the reference's gathered into its layout.
pub fn output_errors(reference: &ModelProto, candidate: &ModelProto, feeds: &Feeds, threads: usize, scene: Option<&SceneView>) -> Result<Vec<OutputError>> {
    ReferenceOutputs::new(reference, feeds, threads, scene)?.errors(candidate)
}

/// A reference model's outputs on some frames, run once, that candidates are measured against:
/// a loop over candidates (pruning's sensitivity, mixed precision) builds the reference's
/// session and runs it once, not once per candidate.
pub struct ReferenceOutputs<'a> {
    names: Vec<String>,
    /// The decoded detection output and its kind: its channel groups are measured apart.
    head: crate::analysis::head::Head,
    /// Per frame, the reference's outputs (under a scene, the detection output gathered to
    /// the scene's cells).
    runs: Vec<Vec<(String, Tensor)>>,
    feeds: &'a Feeds,
    scene: Option<&'a SceneView>,
    threads: usize,
}

impl<'a> ReferenceOutputs<'a> {
    pub fn new(reference: &ModelProto, feeds: &'a Feeds, threads: usize, scene: Option<&'a SceneView>) -> Result<Self> {
        let g = reference.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let graph = Graph::build(g)?;
        let inf = infer(&graph);
        let names: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
        let head = head::detect(&graph, &inf, &names);
        let mut r = OrtRuntime::with_options(reference, GraphOptimizationLevel::Level3, threads)?;
        let mut runs = Vec::with_capacity(feeds.len());
        for feed in feeds {
            let ro = r.run(feed)?;
            runs.push(match scene {
                None => ro,
                Some(s) => ro.into_iter().map(|(n, t)| Ok((n.clone(), if head.output.as_deref() == Some(n.as_str()) { s.gather(&t)? } else { t }))).collect::<Result<Vec<_>>>()?,
            });
        }
        Ok(ReferenceOutputs { names, head, runs, feeds, scene, threads })
    }

    /// [`output_errors`] of `candidate` against these outputs.
    pub fn errors(&self, candidate: &ModelProto) -> Result<Vec<OutputError>> {
        self.errors_at(candidate, GraphOptimizationLevel::Level3)
    }

    /// [`Self::errors`] with the candidate run at `level`: `Disable` keeps a QDQ graph on ONNX
    /// Runtime's reference kernels (float arithmetic on dequantized values, what an integer
    /// accelerator with exact int32 sums computes), where `Level3` fuses it into the CPU's
    /// integer kernels (which saturate with 8-bit weights on x86 without VNNI).
    pub fn errors_at(&self, candidate: &ModelProto, level: GraphOptimizationLevel) -> Result<Vec<OutputError>> {
        Ok(self.measure(candidate, level)?.0)
    }

    /// What pruning a group costs (`prune`'s sensitivity): the worst output group's rel L2,
    /// or, where larger, the confident boxes' error at their own scale ([`BoxErrorSums`]): a
    /// cut to a decoder's box branch moves the boxes' pixel coordinates by little against
    /// their norm and costs the high-IoU part of mAP@0.5:0.95 all the same.
    pub fn damage(&self, candidate: &ModelProto) -> Result<f64> {
        let (errors, boxes) = self.measure(candidate, GraphOptimizationLevel::Level3)?;
        Ok(worst_rel_l2(&errors).max(boxes.finish()))
    }

    fn measure(&self, candidate: &ModelProto, level: GraphOptimizationLevel) -> Result<(Vec<OutputError>, BoxErrorSums)> {
        let mut c = OrtRuntime::with_options(candidate, level, self.threads)?;
        let mut sums: BTreeMap<(usize, Option<&'static str>), ErrorSums> = BTreeMap::new();
        let mut boxes = BoxErrorSums::default();
        for (feed, ro) in self.feeds.iter().zip(&self.runs) {
            let co = match self.scene {
                None => c.run(feed)?,
                Some(s) => c.run(&s.crop_feed(feed)?)?,
            };
            for (k, ((name, a), (_, b))) in ro.iter().zip(&co).enumerate() {
                let (x, y) = (a.data.to_f64(), b.data.to_f64());
                sums.entry((k, None)).or_default().add(x.iter().copied(), y.iter().copied());
                if self.head.output.as_deref() == Some(name.as_str()) {
                    boxes.add(self.head.kind, a, b);
                    for (group, range) in channel_groups(self.head.kind, &a.shape) {
                        let (x, y) = (crate::metrics::validation::select_channels(self.head.kind, a, range.clone()), crate::metrics::validation::select_channels(self.head.kind, b, range));
                        sums.entry((k, Some(group))).or_default().add(x.into_iter(), y.into_iter());
                    }
                }
            }
        }
        Ok((sums.into_iter().map(|((k, group), s)| OutputError { output: self.names[k].clone(), group, error: s.finish() }).collect(), boxes))
    }
}

/// The reference's confident detections on some frames, decoded once, that candidates are
/// scored against (`verify`'s agreement figure: validation's decode and agreement truth).
pub struct DetectionAgreement<'a> {
    head: crate::analysis::head::Head,
    classes: usize,
    truth: Vec<Vec<crate::metrics::coco_map::Truth>>,
    feeds: &'a Feeds,
    threads: usize,
}

impl<'a> DetectionAgreement<'a> {
    /// The reference's detections on `feeds`, or None when its outputs hold no detection head
    /// the decode reads.
    pub fn of(reference: &ModelProto, feeds: &'a Feeds, threads: usize) -> Result<Option<Self>> {
        let g = reference.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
        let graph = Graph::build(g)?;
        let outputs: Vec<String> = g.output.iter().map(|o| o.name.clone()).collect();
        let head = head::detect(&graph, &infer(&graph), &outputs);
        let Some(classes) = head.classes.filter(|_| head.output.is_some()).map(|c| c.max(1)) else { return Ok(None) };
        let theirs = Self::detections(&head, reference, feeds, threads)?;
        let (truth, _) = crate::metrics::validation::agreement_truth(&theirs, classes);
        Ok(Some(DetectionAgreement { head, classes, truth, feeds, threads }))
    }

    /// mAP@0.5:0.95 of `candidate`'s detections against the reference's.
    pub fn score(&self, candidate: &ModelProto) -> Result<f64> {
        let ours = Self::detections(&self.head, candidate, self.feeds, self.threads)?;
        Ok(crate::metrics::coco_map::coco_map(&self.truth, &ours, self.classes).map50_95)
    }

    fn detections(head: &crate::analysis::head::Head, model: &ModelProto, feeds: &Feeds, threads: usize) -> Result<Vec<Vec<crate::detect::Detection>>> {
        let mut rt = OrtRuntime::with_options(model, GraphOptimizationLevel::Level3, threads)?;
        feeds.iter().map(|feed| crate::metrics::validation::detections(head, &rt.run(feed)?)).collect()
    }
}

/// The worst rel L2 over outputs and groups (a group's error when the output has groups).
pub fn worst_rel_l2(errors: &[OutputError]) -> f64 {
    let grouped: std::collections::HashSet<&str> = errors.iter().filter(|e| e.group.is_some()).map(|e| e.output.as_str()).collect();
    errors.iter().filter(|e| e.group.is_some() || !grouped.contains(e.output.as_str())).map(|e| e.error.rel_l2).fold(0.0, f64::max)
}
