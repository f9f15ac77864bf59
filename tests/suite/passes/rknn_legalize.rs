//! `rknn-legalize`: the graph ends at the head convolutions without changing what the
//! detector computes; the split-head post-processing in Rust decodes it exactly like the
//! original in-graph decode.

use crate::common::*;
use crate::target_rknn::compile;
use pdi_compile::analysis::head::HeadKind;
use pdi_compile::detect::decode::candidates;
use pdi_compile::detect::nms::nms;
use pdi_compile::detect::split_head::{decode_dense, detect, HeadLayout};
use pdi_compile::runtime::{ort_runtime::OrtRuntime, Runtime};
use std::collections::HashMap;

/// Same frame through the original (in-graph decode) and the legalized model: the Rust
/// decode of the split outputs equals the original's decoded tensor, and the deployment
/// path (score skipping + NMS) equals NMS over the original's candidates.
#[test]
fn split_head_post_processing_equals_the_in_graph_decode() {
    let dir = tempfile::tempdir().unwrap();
    for (model, kind) in [("models/trained/pdinet_v5_tiny_trained.onnx", HeadKind::Yolov5Anchor), ("models/fixtures/pdinet_v8_input_op17_nofold.onnx", HeadKind::Yolov8Dfl)] {
        let (orig_dir, legal_dir) = (dir.path().join("orig"), dir.path().join("legal"));
        assert_eq!(compile(model, "passes/detect-f32.yaml", &orig_dir, &[]).code, 0);
        let r = compile(model, "passes/detect-rknn.yaml", &legal_dir, &[]);
        assert_eq!(r.code, 0, "{}", r.stderr);
        let (orig, legal) = (load(&orig_dir.join("model.onnx")), load(&legal_dir.join("model.onnx")));
        let layout = HeadLayout::from_model(&legal).unwrap();
        assert_eq!(layout.kind, kind);
        assert!(legal.ir_version <= 9);
        let g = legal.graph.as_ref().unwrap();
        let outputs: Vec<&str> = g.output.iter().map(|o| o.name.as_str()).collect();
        assert_eq!(outputs, layout.output_names().iter().map(String::as_str).collect::<Vec<_>>());
        for o in &g.output {
            let producer = g.node.iter().find(|n| n.output.contains(&o.name)).unwrap();
            assert!(["Conv", "Sigmoid", "Clip"].contains(&producer.op_type.as_str()), "{} ends in {}", o.name, producer.op_type);
        }
        assert!(!g.node.iter().any(|n| ["Reshape", "Transpose", "Softmax", "Pow"].contains(&n.op_type.as_str())), "no decode left");

        let feeds = inputs_for(&orig, 3);
        let original = OrtRuntime::new(&orig).unwrap().run(&feeds).unwrap().remove(0).1;
        let split: HashMap<_, _> = OrtRuntime::new(&legal).unwrap().run(&feeds).unwrap().into_iter().collect();
        let dense = decode_dense(&layout, &split).unwrap();
        assert_eq!(dense.shape, original.shape);
        let worst = original.as_f32().unwrap().iter().zip(dense.as_f32().unwrap()).map(|(a, b)| (a - b).abs() / a.abs().max(1.0)).fold(0f32, f32::max);
        println!("{model}: split decode vs in-graph decode, worst relative difference {worst:.2e}");
        assert!(worst <= 1e-4, "{worst}");

        let conf = if kind == HeadKind::Yolov5Anchor { 0.25 } else { 0.02 };
        let expected = nms(candidates(kind, &original, conf).unwrap(), 0.45, 300);
        let (got, skipped) = detect(&layout, &split, conf, 0.45, 300).unwrap();
        assert!(!expected.is_empty(), "{model}: the frame has detections to compare");
        assert_eq!(got.len(), expected.len(), "{model}");
        for (a, b) in got.iter().zip(&expected) {
            assert_eq!(a.class, b.class);
            assert!((a.score - b.score).abs() <= 1e-4 && a.bbox.iter().zip(&b.bbox).all(|(x, y)| (x - y).abs() <= 1e-2), "{a:?} vs {b:?}");
        }
        println!("  {} detections; {} of {} cells skipped before decoding", got.len(), skipped.skipped, skipped.cells);
        assert!(skipped.skipped > 0);
    }
}
