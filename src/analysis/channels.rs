//! Channel dependency groups: which channels of which values must be pruned together.
//!
//! Every channel of every 4-D NCHW value is a *slot*. Ops that tie channels one to one
//! (activations, BatchNorm, residual Add/Mul, depthwise conv, pooling, Resize) unite slots;
//! Concat, Split and Slice on the channel axis unite them at an offset. A *class* (a
//! union-find root) is one prunable unit: removing it removes every slot it holds, in every
//! value, at once. Dense convolutions end the chain: their inputs are consumed, their outputs
//! are new channels. A *group* gathers the classes that live in the same run of one-to-one
//! coupled values (a residual stage, an SE-gated feature map, one branch of a Concat) and is
//! what the pruning ratio applies to.
//!
//! Anything the analysis cannot see through (Reshape, Transpose, Gemm, a non-constant
//! weight, an unknown op) *fixes* the slots of its operands: a fixed class is never pruned,
//! and its group is reported as frozen with the reason. Wrong pruning is not possible by
//! construction; too little pruning is, and shows in the report.

use crate::ir::{Graph, Inferred};
use crate::onnx::attr;
use crate::onnx::tensor_proto::to_tensor;
use std::collections::{BTreeMap, HashMap, HashSet};

/// Ops whose output channel c is a function of input channel c only.
const CHANNELWISE_UNARY: &[&str] = &[
    "Relu", "Sigmoid", "Tanh", "LeakyRelu", "Elu", "Selu", "Celu", "HardSigmoid", "HardSwish", "Softplus", "Softsign", "Mish", "Gelu",
    "Identity", "Dropout", "Neg", "Abs", "Exp", "Log", "Sqrt", "Reciprocal", "Erf", "Floor", "Ceil", "Round", "Sign", "Sin", "Cos",
    "MaxPool", "AveragePool", "LpPool", "GlobalAveragePool", "GlobalMaxPool", "GlobalLpPool", "Clip", "Cast", "Resize", "Upsample",
];
/// Element-wise ops with broadcasting: operands with the output's channel count are tied to it.
const BROADCAST_BINARY: &[&str] = &["Add", "Sub", "Mul", "Div", "Max", "Min", "Sum", "Mean", "Pow", "PRelu"];

#[derive(Clone, Copy, Debug)]
pub struct Slots {
    pub offset: usize,
    pub channels: usize,
}

/// A set of classes pruned at one ratio.
#[derive(Clone, Debug)]
pub struct Group {
    /// Class ids (indices into [`ChannelAnalysis::class_slots`]), in the channel order of `anchor`.
    pub classes: Vec<usize>,
    /// The values whose channels are exactly this group's classes (one-to-one coupled).
    pub values: Vec<String>,
    /// The first of `values` in graph order: names the group in reports.
    pub anchor: String,
    /// Why the group cannot be pruned, if it cannot.
    pub frozen: Option<String>,
    /// Values split into equal segments by a grouped convolution: each segment must keep
    /// as many channels as every other (value, segment count).
    pub segments: Vec<(String, usize)>,
}

pub struct ChannelAnalysis {
    pub values: BTreeMap<String, Slots>,
    /// Slot -> class id.
    pub class_of: Vec<usize>,
    /// Class id -> its slots.
    pub class_slots: Vec<Vec<usize>>,
    pub groups: Vec<Group>,
    /// Class id -> group index.
    pub group_of: Vec<usize>,
}

impl ChannelAnalysis {
    /// Class ids of `value`'s channels, in channel order.
    pub fn classes_of(&self, value: &str) -> Option<Vec<usize>> {
        let s = self.values.get(value)?;
        Some((s.offset..s.offset + s.channels).map(|i| self.class_of[i]).collect())
    }
}

struct Builder {
    values: BTreeMap<String, Slots>,
    value_index: HashMap<String, usize>,
    slot_value: Vec<usize>,
    parent: Vec<usize>,
    fixed: Vec<Option<String>>,
    value_parent: Vec<usize>,
    segments: Vec<(String, usize)>,
}

fn find(p: &mut [usize], mut x: usize) -> usize {
    while p[x] != x {
        p[x] = p[p[x]];
        x = p[x];
    }
    x
}

impl Builder {
    fn slots(&self, v: &str) -> Option<Slots> {
        self.values.get(v).copied()
    }

    fn unite(&mut self, a: usize, b: usize) {
        let (ra, rb) = (find(&mut self.parent, a), find(&mut self.parent, b));
        if ra != rb {
            self.parent[ra.max(rb)] = ra.min(rb);
        }
    }

    /// Ties channel `i` of `a` to channel `i` of `b` for every i (same channel count).
    fn couple(&mut self, a: &str, b: &str) -> bool {
        let (Some(sa), Some(sb)) = (self.slots(a), self.slots(b)) else { return false };
        if sa.channels != sb.channels {
            return false;
        }
        for i in 0..sa.channels {
            self.unite(sa.offset + i, sb.offset + i);
        }
        let (va, vb) = (self.value_index[a], self.value_index[b]);
        let (ra, rb) = (find(&mut self.value_parent, va), find(&mut self.value_parent, vb));
        if ra != rb {
            self.value_parent[ra.max(rb)] = ra.min(rb);
        }
        true
    }

    /// Ties channels `[at, at + part.channels)` of `whole` to the channels of `part`.
    fn couple_at(&mut self, whole: &str, at: usize, part: &str) -> bool {
        let (Some(sw), Some(sp)) = (self.slots(whole), self.slots(part)) else { return false };
        if at + sp.channels > sw.channels {
            return false;
        }
        for i in 0..sp.channels {
            self.unite(sw.offset + at + i, sp.offset + i);
        }
        true
    }

    /// Ties `parts`, laid end to end, to the channels of `whole` (Concat inputs, Split
    /// outputs); false unless they cover it exactly.
    fn couple_parts(&mut self, whole: &str, parts: &[String]) -> bool {
        let mut at = 0;
        for p in parts {
            if !self.couple_at(whole, at, p) {
                return false;
            }
            at += self.slots(p).map_or(0, |s| s.channels);
        }
        self.slots(whole).is_some_and(|s| s.channels == at)
    }

    fn fix(&mut self, v: &str, why: &str) {
        if let Some(s) = self.slots(v) {
            for i in s.offset..s.offset + s.channels {
                self.fixed[i].get_or_insert_with(|| why.to_string());
            }
        }
    }
}

/// Analyses `g`. `protected` names values (or nodes, whose outputs are then protected) that
/// must keep every channel.
pub fn analyse(g: &Graph, inf: &Inferred, protected: &[String]) -> ChannelAnalysis {
    let mut b = Builder { values: BTreeMap::new(), value_index: HashMap::new(), slot_value: Vec::new(), parent: Vec::new(), fixed: Vec::new(), value_parent: Vec::new(), segments: Vec::new() };
    let mut names: Vec<&str> = g.inputs.iter().map(|v| v.name.as_str()).collect();
    for &i in &g.order {
        names.extend(g.node(i).output.iter().filter(|o| !o.is_empty()).map(String::as_str));
    }
    for name in names {
        let Some(shape) = inf.shape(name) else { continue };
        if shape.len() != 4 || shape[1] == 0 || b.values.contains_key(name) {
            continue;
        }
        let offset = b.parent.len();
        let vi = b.value_index.len();
        b.value_index.insert(name.to_string(), vi);
        b.value_parent.push(vi);
        for k in 0..shape[1] {
            b.parent.push(offset + k);
            b.fixed.push(None);
            b.slot_value.push(vi);
        }
        b.values.insert(name.to_string(), Slots { offset, channels: shape[1] });
    }

    for v in &g.inputs {
        b.fix(&v.name, "graph input");
    }
    for o in &g.proto.output {
        b.fix(&o.name, "graph output");
    }
    for p in protected {
        b.fix(p, "protected by the recipe");
        if let Some(n) = g.proto.node.iter().find(|n| &n.name == p) {
            for o in &n.output {
                b.fix(o, "protected by the recipe");
            }
        }
    }
    for conv in head_convolutions(g) {
        b.fix(&g.node(conv).output[0], "detection head output convolution");
    }
    for &i in &g.order {
        relate(&mut b, g, inf, i);
    }
    finish(b)
}

/// Convolutions whose output reaches a graph output without passing another convolution:
/// the detector's last layers, whose channel layout is the output format.
pub(crate) fn head_convolutions(g: &Graph) -> Vec<usize> {
    head_convolutions_through(g, |_| false)
}

/// The detector's last convolutions, past a YOLOv8 DFL's fixed arange convolution (the one
/// convolution that reads a Softmax: it belongs to the decode, not to the detector).
pub(crate) fn detector_convolutions(g: &Graph) -> Vec<usize> {
    head_convolutions_through(g, |n| g.producer_of(&n.input[0]).is_some_and(|p| p.op_type == "Softmax"))
}

/// Nodes of the in-graph decode: everything after the detector's last convolutions. Their
/// constants (anchors, grids, the DFL arange) are fixed by the format, never fitted.
pub(crate) fn decode_nodes(g: &Graph) -> HashSet<usize> {
    g.downstream_of(&detector_convolutions(g).into_iter().collect())
}

/// [`head_convolutions`], looking past the convolutions `transparent` accepts (a YOLOv8
/// DFL's fixed arange convolution is part of the decode, not of the detector).
fn head_convolutions_through(g: &Graph, transparent: impl Fn(&crate::onnx::proto::NodeProto) -> bool) -> Vec<usize> {
    let mut found = Vec::new();
    let mut seen = HashSet::new();
    let mut stack: Vec<&str> = g.proto.output.iter().map(|o| o.name.as_str()).collect();
    while let Some(v) = stack.pop() {
        let Some(&i) = g.producer.get(v) else { continue };
        if !seen.insert(i) {
            continue;
        }
        let n = g.node(i);
        if matches!(n.op_type.as_str(), "Conv" | "ConvTranspose") && !transparent(n) {
            found.push(i);
        } else {
            stack.extend(n.input.iter().filter(|s| !s.is_empty() && !g.initializers.contains_key(s.as_str())).map(String::as_str));
        }
    }
    found
}

fn relate(b: &mut Builder, g: &Graph, inf: &Inferred, i: usize) {
    let n = g.node(i);
    let why = format!("{} '{}' is not analysed for pruning", n.op_type, n.name);
    let fix_all = |b: &mut Builder, why: &str| {
        for v in n.input.iter().chain(&n.output) {
            b.fix(v, why);
        }
    };
    let constant = |name: &str| g.initializers.contains_key(name);
    let ok = n.domain.is_empty()
        && match n.op_type.as_str() {
            "Conv" | "ConvTranspose" => relate_conv(b, g, n),
            "BatchNormalization" => n.output.iter().skip(1).all(|o| o.is_empty()) && n.input[1..].iter().all(|p| constant(p)) && b.couple(&n.input[0], &n.output[0]),
            "Concat" => channel_axis(n) && b.couple_parts(&n.output[0], &n.input),
            "Split" => channel_axis(n) && b.couple_parts(&n.input[0], &n.output),
            "Slice" => relate_slice(b, g, n),
            op if op == "Resize" || op == "Upsample" => b.couple(&n.input[0], &n.output[0]) && resize_keeps_channels(g, n),
            "Clip" => n.input.iter().skip(1).all(|s| s.is_empty() || constant(s)) && b.couple(&n.input[0], &n.output[0]),
            op if CHANNELWISE_UNARY.contains(&op) => b.couple(&n.input[0], &n.output[0]),
            op if BROADCAST_BINARY.contains(&op) => relate_broadcast(b, g, inf, n),
            _ => false,
        };
    if !ok {
        fix_all(b, &why);
    }
}

/// Concat/Split along axis 1 of a 4-D value.
fn channel_axis(n: &crate::onnx::proto::NodeProto) -> bool {
    matches!(attr::int(n, "axis", 0), 1 | -3)
}

fn relate_conv(b: &mut Builder, g: &Graph, n: &crate::onnx::proto::NodeProto) -> bool {
    let consts = n.input.iter().skip(1).all(|s| s.is_empty() || g.initializers.contains_key(s.as_str()));
    let (Some(x), Some(y)) = (b.slots(&n.input[0]), b.slots(&n.output[0])) else { return false };
    if !consts {
        return false;
    }
    let group = attr::int(n, "group", 1).max(1) as usize;
    if group == 1 {
        return true;
    }
    if group == x.channels && x.channels == y.channels {
        return b.couple(&n.input[0], &n.output[0]);
    }
    // Grouped (not depthwise), Conv only: equal pruning per segment keeps the groups valid.
    if n.op_type == "Conv" && x.channels % group == 0 && y.channels % group == 0 && group < x.channels {
        b.segments.push((n.input[0].clone(), group));
        b.segments.push((n.output[0].clone(), group));
        return true;
    }
    false
}

fn relate_slice(b: &mut Builder, g: &Graph, n: &crate::onnx::proto::NodeProto) -> bool {
    let read = |k: usize| -> Option<Vec<i64>> {
        let name = n.input.get(k).filter(|s| !s.is_empty())?;
        to_tensor(g.initializers.get(name.as_str())?).ok()?.as_i64s()
    };
    let (Some(x), Some(y)) = (b.slots(&n.input[0]), b.slots(&n.output[0])) else { return false };
    let (Some(starts), Some(_)) = (read(1), read(2)) else { return false };
    let axes = read(3).unwrap_or_else(|| (0..starts.len() as i64).collect());
    let steps = read(4).unwrap_or_else(|| vec![1; starts.len()]);
    match axes.iter().position(|&a| a == 1 || a == -3) {
        None => b.couple(&n.input[0], &n.output[0]),
        Some(k) => {
            if steps.get(k) != Some(&1) {
                return false;
            }
            let c = x.channels as i64;
            let start = if starts[k] < 0 { starts[k] + c } else { starts[k] }.clamp(0, c) as usize;
            start + y.channels <= x.channels && b.couple_at(&n.input[0], start, &n.output[0])
        }
    }
}

fn resize_keeps_channels(g: &Graph, n: &crate::onnx::proto::NodeProto) -> bool {
    // Scales on N and C must be 1 (sizes inputs are rewritten when channels go).
    let scales = n.input.get(2).filter(|s| !s.is_empty()).and_then(|s| g.initializers.get(s.as_str())).and_then(|t| to_tensor(t).ok());
    scales.is_none_or(|t| t.as_f32().is_none_or(|v| v.len() < 2 || (v[0] == 1.0 && v[1] == 1.0)))
}

fn relate_broadcast(b: &mut Builder, g: &Graph, inf: &Inferred, n: &crate::onnx::proto::NodeProto) -> bool {
    let Some(y) = b.slots(&n.output[0]) else { return false };
    for x in n.input.iter().filter(|s| !s.is_empty()) {
        if let Some(t) = g.initializers.get(x.as_str()) {
            // A constant's channel axis is its third dimension from the right.
            let r = t.dims.len();
            if r >= 3 && t.dims[r - 3] != 1 && t.dims[r - 3] as usize != y.channels {
                return false;
            }
            continue;
        }
        match b.slots(x) {
            Some(s) if s.channels == y.channels => {
                b.couple(x, &n.output[0]);
            }
            Some(s) if s.channels == 1 => {}
            Some(_) => return false,
            None => match inf.shape(x) {
                // A computed scalar or [H, W] plane: channel-agnostic.
                Some(s) if s.len() < 3 => {}
                _ => return false,
            },
        }
    }
    true
}

fn finish(mut b: Builder) -> ChannelAnalysis {
    let n = b.parent.len();
    let roots: Vec<usize> = (0..n).map(|s| find(&mut b.parent, s)).collect();
    let mut class_index: HashMap<usize, usize> = HashMap::new();
    let mut class_slots: Vec<Vec<usize>> = Vec::new();
    let mut class_of = vec![0; n];
    for s in 0..n {
        let next = class_slots.len();
        let c = *class_index.entry(roots[s]).or_insert(next);
        if c == next {
            class_slots.push(Vec::new());
        }
        class_slots[c].push(s);
        class_of[s] = c;
    }
    let names: Vec<String> = {
        let mut v = vec![String::new(); b.value_index.len()];
        for (k, &i) in &b.value_index {
            v[i] = k.clone();
        }
        v
    };
    // Home of a class: the coupled run of values with the fewest channels among those it
    // touches (a Concat branch rather than the Concat), first in graph order on ties.
    let vcomp: Vec<usize> = (0..names.len()).map(|v| find(&mut b.value_parent, v)).collect();
    let home: Vec<usize> = class_slots
        .iter()
        .map(|slots| {
            slots.iter().map(|&s| vcomp[b.slot_value[s]]).min_by_key(|&c| (b.values[&names[c]].channels, c)).expect("a class has a slot")
        })
        .collect();
    let mut by_home: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (c, &h) in home.iter().enumerate() {
        by_home.entry(h).or_default().push(c);
    }
    // Segment constraints must stay inside one group, one channel per class.
    let segments = std::mem::take(&mut b.segments);
    let mut group_segments: HashMap<usize, Vec<(String, usize)>> = HashMap::new();
    for (v, parts) in segments {
        let s = b.values[&v];
        let cls: Vec<usize> = (s.offset..s.offset + s.channels).map(|i| class_of[i]).collect();
        let h = home[cls[0]];
        let distinct = cls.iter().collect::<HashSet<_>>().len() == cls.len();
        if distinct && cls.iter().all(|&c| home[c] == h) && by_home[&h].len() == cls.len() {
            group_segments.entry(h).or_default().push((v, parts));
        } else {
            b.fix(&v, "grouped convolution whose channels mix pruning groups");
        }
    }
    let mut groups = Vec::new();
    let mut group_of = vec![0; class_slots.len()];
    for (h, classes) in by_home {
        let anchor = names[h].clone();
        // Channel order of the anchor where it holds the classes (it does, being the home).
        let a = b.values[&anchor];
        let mut ordered: Vec<usize> = Vec::new();
        for i in a.offset..a.offset + a.channels {
            if !ordered.contains(&class_of[i]) {
                ordered.push(class_of[i]);
            }
        }
        let members: HashSet<usize> = classes.iter().copied().collect();
        ordered.retain(|c| members.contains(c));
        for c in &classes {
            if !ordered.contains(c) {
                ordered.push(*c);
            }
        }
        let frozen = ordered.iter().flat_map(|&c| class_slots[c].iter()).find_map(|&s| b.fixed[s].clone());
        let values: Vec<String> = (0..names.len()).filter(|&v| vcomp[v] == h).map(|v| names[v].clone()).collect();
        for &c in &ordered {
            group_of[c] = groups.len();
        }
        groups.push(Group { classes: ordered, values, anchor, frozen, segments: group_segments.remove(&h).unwrap_or_default() });
    }
    ChannelAnalysis { values: b.values, class_of, class_slots, groups, group_of }
}
