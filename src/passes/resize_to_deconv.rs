//! `resize-to-deconv`: nearest-neighbour upsampling by integer factors becomes a depthwise
//! ConvTranspose with a ones kernel and stride = factor.
//!
//! With kernel = stride the transposed convolution's windows do not overlap, so each output
//! pixel is exactly one input pixel times 1.0: bit-exact. It is the same block copy as
//! Resize(nearest) under `asymmetric` + `floor` (PyTorch's export) and under `half_pixel` +
//! `round_prefer_floor`, where source coordinates (y + 0.5)/s - 0.5 stay strictly inside
//! (k - 0.5, k + 0.5) for the block of input pixel k. Other modes are left alone.
//! Why: NPUs run deconvolution natively while Resize often falls back to the CPU, and a
//! graph without Resize has no coordinate-mode ambiguity between runtimes.
//! Needs: constant scales or sizes, static input shape. Reports: Resizes replaced and left.

use crate::ir::{infer, Graph};
use crate::onnx::attr;
use crate::onnx::edit::{fresh_name, set_initializer};
use crate::onnx::proto::{ModelProto, NodeProto};
use crate::onnx::tensor_proto::from_tensor;
use super::{Pass, PassContext};
use crate::tensor::Tensor;
use anyhow::Result;

pub struct ResizeToDeconv;

/// Integer (sh, sw) factors when `n` is a nearest block-copy upsampling of a [N, C, H, W] input.
fn block_copy_factors(n: &NodeProto, input: &[usize], output: &[usize]) -> Result<(usize, usize), String> {
    if n.op_type != "Resize" || input.len() != 4 || output.len() != 4 {
        return Err("not a 4-D Resize".into());
    }
    let mode = attr::string(n, "mode", "nearest");
    let ctm = attr::string(n, "coordinate_transformation_mode", "half_pixel");
    let nearest = attr::string(n, "nearest_mode", "round_prefer_floor");
    let exact = mode == "nearest" && ((ctm == "asymmetric" && nearest == "floor") || (matches!(ctm.as_str(), "half_pixel" | "pytorch_half_pixel") && nearest == "round_prefer_floor"));
    if !exact {
        return Err(format!("mode {mode}/{ctm}/{nearest} is not a plain block copy"));
    }
    if output[0] != input[0] || output[1] != input[1] || !output[2].is_multiple_of(input[2]) || !output[3].is_multiple_of(input[3]) {
        return Err(format!("{input:?} -> {output:?} is not an integer upsampling"));
    }
    let (sh, sw) = (output[2] / input[2], output[3] / input[3]);
    if ctm == "pytorch_half_pixel" && (output[2] == 1 || output[3] == 1) {
        return Err("pytorch_half_pixel with a unit output dimension".into());
    }
    Ok((sh, sw))
}

impl Pass for ResizeToDeconv {
    fn name(&self) -> &'static str {
        "resize-to-deconv"
    }

    fn run(&self, model: &mut ModelProto, _: &mut PassContext) -> Result<serde_json::Value> {
        let plans: Vec<(usize, Result<(usize, usize, usize), String>)> = {
            let g = model.graph.as_ref().expect("checked by the pipeline");
            let graph = Graph::build(g)?;
            let inf = infer(&graph);
            g.node
                .iter()
                .enumerate()
                .filter(|(_, n)| n.op_type == "Resize")
                .map(|(i, n)| {
                    let plan = match (inf.shape(&n.input[0]), inf.shape(&n.output[0]), inf.types.get(&n.input[0]).and_then(|t| t.dtype)) {
                        (Some(a), Some(b), Some(crate::tensor::DType::F32)) => block_copy_factors(n, &a, &b).map(|(sh, sw)| (a[1], sh, sw)),
                        _ => Err("shape or float32 type unknown".into()),
                    };
                    (i, plan)
                })
                .collect()
        };
        let g = super::graph_mut(model)?;
        let (mut replaced, mut left) = (Vec::new(), Vec::new());
        for (i, plan) in plans {
            let name = g.node[i].name.clone();
            match plan {
                Ok((c, sh, sw)) => {
                    let wn = fresh_name(g, &format!("{}_ones", if name.is_empty() { "upsample" } else { &name }));
                    set_initializer(g, from_tensor(&wn, &Tensor::f32(vec![c, 1, sh, sw], vec![1.0; c * sh * sw])));
                    let old = g.node[i].clone();
                    g.node[i] = NodeProto {
                        name: old.name.clone(),
                        op_type: "ConvTranspose".into(),
                        input: vec![old.input[0].clone(), wn],
                        output: vec![old.output[0].clone()],
                        attribute: vec![
                            attr::make_int("group", c as i64),
                            attr::make_ints("kernel_shape", vec![sh as i64, sw as i64]),
                            attr::make_ints("strides", vec![sh as i64, sw as i64]),
                        ],
                        doc_string: old.doc_string,
                        metadata_props: old.metadata_props,
                        ..Default::default()
                    };
                    replaced.push(serde_json::json!({ "node": name, "factors": [sh, sw], "channels": c }));
                }
                Err(reason) => left.push(serde_json::json!({ "node": name, "reason": reason })),
            }
        }
        crate::ir::rewrite::dce::eliminate(g)?;
        Ok(serde_json::json!({ "replaced": replaced, "left": left }))
    }
}
