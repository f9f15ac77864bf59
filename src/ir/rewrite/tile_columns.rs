//! A convolution split into several over column tiles of its input, concatenated along the
//! width (the `tile-conv-columns` pass; the tract target picks the convolutions by timing).
//! Each tile is the original over its columns, with the original's padding on the frame's
//! edges only: every output is the original's products.

use crate::ir::graph::Graph;
use crate::ir::shapes::{infer, Inferred};
use crate::onnx::attr;
use crate::onnx::edit::{add_constant, default_opset, fresh_name, initializer};
use crate::onnx::proto::{GraphProto, ModelProto, NodeProto};
use crate::tensor::{Tensor, TensorData};
use anyhow::Result;

/// The widest tile input: tract-core 0.23 takes the direct spatial path only for rows of at
/// least 128 points (`MIN_DIRECT_SPATIAL_W` in its `conv.rs`).
pub const MAX_TILE_WIDTH: usize = 127;
/// tract-core 0.23's direct spatial convolution takes at most this many inputs per output
/// point on hosts without Apple's AMX (`can_direct_spatial`); wider ones are matrix products
/// already, so tiling them changes nothing.
pub const DIRECT_MAX_K: usize = 576;
/// More tiles than this cost more in slicing and concatenation than any kernel choice saves.
const MAX_TILES: usize = 16;

/// How one convolution is tiled: per tile, its input columns [start, end) and its left and
/// right padding.
#[derive(Clone, Debug)]
pub struct Plan {
    pub node: String,
    /// The input's shape, [N, C, H, W].
    pub input: Vec<usize>,
    pub width: usize,
    pub tiles: Vec<Tile>,
}

#[derive(Clone, Debug, PartialEq)]
pub struct Tile {
    pub columns: std::ops::Range<usize>,
    pub pads: [usize; 2],
}

/// Every convolution tract-core 0.23 would run as its direct spatial convolution, by name:
/// its tiling, or why it has none.
pub fn candidates(model: &ModelProto) -> Result<Vec<(String, Result<Plan, String>)>> {
    let g = model.graph.as_ref().ok_or_else(|| anyhow::anyhow!("model has no graph"))?;
    let ir = Graph::build(g)?;
    let shapes = infer(&ir);
    let opset = default_opset(model).unwrap_or(0);
    // Convolutions are addressed by name, so only a name that is there once can be tiled.
    let mut names: std::collections::HashMap<&str, usize> = std::collections::HashMap::new();
    for n in &g.node {
        *names.entry(n.name.as_str()).or_default() += 1;
    }
    Ok(g.node
        .iter()
        .filter(|n| !n.name.is_empty() && names[n.name.as_str()] == 1)
        .filter_map(|n| direct_spatial(g, n, &shapes).map(|input| (n.name.clone(), plan(n, &input, opset))))
        .collect())
}

/// The input shape of `n` when tract-core 0.23 would run it as a direct spatial convolution
/// (f32, group 1, 2-D, 2 to [`DIRECT_MAX_K`] inputs per output point, rows of 128 or more).
fn direct_spatial(g: &GraphProto, n: &NodeProto, shapes: &Inferred) -> Option<Vec<usize>> {
    if n.op_type != "Conv" || attr::int(n, "group", 1) != 1 {
        return None;
    }
    let w = initializer(g, n.input.get(1)?)?;
    let input = shapes.shape(&n.input[0])?;
    let (&[_, c, kh, kw], &[_, _, _, width]) = (&w.dims[..], &input[..]) else { return None };
    let taps = (kh * kw) as usize;
    (w.data_type == 1 && taps >= 2 && c as usize * taps <= DIRECT_MAX_K && width > MAX_TILE_WIDTH).then_some(input)
}

fn plan(n: &NodeProto, input: &[usize], opset: i64) -> Result<Plan, String> {
    if opset < 10 {
        return Err(format!("opset {opset}: Slice takes its bounds as inputs from opset 10"));
    }
    if !matches!(attr::string(n, "auto_pad", "NOTSET").as_str(), "NOTSET" | "") {
        return Err("auto_pad instead of explicit pads".into());
    }
    let k = attr::ints(n, "kernel_shape").unwrap_or_default();
    let pads = attr::ints(n, "pads").unwrap_or(vec![0; 4]);
    let strides = attr::ints(n, "strides").unwrap_or(vec![1, 1]);
    let dilations = attr::ints(n, "dilations").unwrap_or(vec![1, 1]);
    if k.len() != 2 || pads.len() != 4 || strides.len() != 2 || dilations.len() != 2 || k.iter().chain(&pads).any(|&v| v < 0) || strides.iter().chain(&dilations).any(|&v| v < 1) {
        return Err(format!("kernel {k:?}, pads {pads:?}, strides {strides:?}, dilations {dilations:?} are not a 2-D convolution's"));
    }
    let width = input[3];
    let (span, s, [pl, pr]) = (((k[1] - 1) * dilations[1] + 1) as usize, strides[1] as usize, [pads[1] as usize, pads[3] as usize]);
    let Some(outputs) = (width + pl + pr).checked_sub(span).map(|r| r / s + 1) else {
        return Err(format!("its {span}-column kernel is wider than its padded {width}-column input"));
    };
    if outputs <= MAX_TILE_WIDTH {
        return Err(format!("its output rows are {outputs} wide: tract runs it as a matrix product already"));
    }
    for count in 2..=MAX_TILES.min(outputs) {
        let tiles = split(outputs, count, width, span, s, pl);
        if tiles.iter().all(|t| t.columns.len() <= MAX_TILE_WIDTH) {
            return Ok(Plan { node: n.name.clone(), input: input.to_vec(), width, tiles });
        }
    }
    Err(format!("{MAX_TILES} tiles of its {width} columns still read more than {MAX_TILE_WIDTH} each"))
}

/// `outputs` output columns in `count` runs as even as can be, and the input columns each
/// reads: output column o reads the padded input from o*s to o*s + span - 1.
fn split(outputs: usize, count: usize, width: usize, span: usize, s: usize, pad_left: usize) -> Vec<Tile> {
    (0..count)
        .map(|t| {
            let (a, b) = (t * outputs / count, (t + 1) * outputs / count);
            // In padded coordinates; the padding is whatever falls outside the frame.
            let (lo, hi) = (a * s, (b - 1) * s + span);
            let start = lo.saturating_sub(pad_left).min(width);
            let end = hi.saturating_sub(pad_left).min(width);
            Tile { columns: start..end, pads: [pad_left.saturating_sub(lo), (hi - pad_left).saturating_sub(width)] }
        })
        .collect()
}

/// Replaces the convolution of `plan` by its tiles: a Slice of the input, the convolution
/// with its tile's padding, per tile, and a Concat along the width.
pub fn tile(g: &mut GraphProto, plan: &Plan) -> Result<()> {
    let i = g.node.iter().position(|n| n.name == plan.node).ok_or_else(|| anyhow::anyhow!("no node named '{}'", plan.node))?;
    let old = g.node[i].clone();
    let pads = attr::ints(&old, "pads").unwrap_or(vec![0; 4]);
    let int = |g: &mut GraphProto, base: &str, v: i64| add_constant(g, base, &Tensor::new(vec![1], TensorData::I64(vec![v])));
    let axis = int(g, &format!("{}_width_axis", old.name), 3);
    let mut nodes = Vec::new();
    let mut outputs = Vec::new();
    for (t, tile) in plan.tiles.iter().enumerate() {
        let base = format!("{}_tile{t}", old.name);
        let start = int(g, &format!("{base}_start"), tile.columns.start as i64);
        let end = int(g, &format!("{base}_end"), tile.columns.end as i64);
        let (columns, out) = (fresh_name(g, &format!("{base}_columns")), fresh_name(g, &base));
        nodes.push(NodeProto { name: format!("{base}_columns"), op_type: "Slice".into(), input: vec![old.input[0].clone(), start, end, axis.clone()], output: vec![columns.clone()], ..Default::default() });
        let mut conv = old.clone();
        conv.name = base;
        conv.input[0] = columns;
        conv.output = vec![out.clone()];
        conv.attribute.retain(|a| a.name != "pads");
        conv.attribute.push(attr::make_ints("pads", vec![pads[0], tile.pads[0] as i64, pads[2], tile.pads[1] as i64]));
        nodes.push(conv);
        outputs.push(out);
    }
    nodes.push(NodeProto { name: format!("{}_tiles", old.name), op_type: "Concat".into(), input: outputs, output: old.output.clone(), attribute: vec![attr::make_int("axis", 3)], ..Default::default() });
    g.node.splice(i..=i, nodes);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_read_their_neighbours_columns_and_pad_only_the_frame_edges() {
        // 3 taps, pad 1, stride 1: 300 outputs in 3 tiles of 100, each reading one column
        // beyond its own on each inner side.
        let t = split(300, 3, 300, 3, 1, 1);
        assert_eq!(t, vec![Tile { columns: 0..101, pads: [1, 0] }, Tile { columns: 99..201, pads: [0, 0] }, Tile { columns: 199..300, pads: [0, 1] }]);
        // Stride 2, dilation 2 (span 5), pads 2 / 1 on 301 columns: 150 outputs.
        let t = split(150, 2, 301, 5, 2, 2);
        assert_eq!(t[0], Tile { columns: 0..151, pads: [2, 0] });
        // The last output (149) reads padded columns 298..303, input 296..301: inside the
        // frame, so this tile needs none of the original's right padding.
        assert_eq!(t[1], Tile { columns: 148..301, pads: [0, 0] });
        for tile in &t {
            let padded = tile.columns.len() + tile.pads[0] + tile.pads[1];
            assert_eq!((padded - 5) / 2 + 1, 75, "{tile:?}");
        }
    }
}
