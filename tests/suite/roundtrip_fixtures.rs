//! Every committed fixture survives load -> save unchanged, and runs the same.

use crate::common::*;
use pdi_compile::runtime::{self, Engine};
use prost::Message;

#[test]
fn fixtures_round_trip_byte_for_byte() {
    for f in fixtures() {
        let bytes = std::fs::read(&f).unwrap();
        let loaded = pdi_compile::onnx::load_bytes(&bytes, f.parent()).unwrap();
        assert!(loaded.warnings.is_empty(), "{}: {:?}", f.display(), loaded.warnings);
        assert!(loaded.model.encode_to_vec() == bytes, "{}: re-encoded bytes differ", f.display());
    }
}

#[test]
fn saved_fixtures_give_bit_identical_ort_outputs() {
    let dir = tempfile::tempdir().unwrap();
    for f in fixtures() {
        let original = load(&f);
        let saved_path = dir.path().join("saved.onnx");
        pdi_compile::onnx::save(&original, &saved_path).unwrap();
        let saved = load(&saved_path);
        let inputs = inputs_for(&original, 7);
        let a = runtime::load(Engine::Ort, &original, &inputs, 1).unwrap().run(&inputs).unwrap();
        let b = runtime::load(Engine::Ort, &saved, &inputs, 1).unwrap().run(&inputs).unwrap();
        assert_eq!(a.len(), 2);
        for ((na, ta), (nb, tb)) in a.iter().zip(&b) {
            assert_eq!(na, nb);
            assert!(ta.bit_identical(tb), "{}: output {na} differs after save", f.display());
        }
    }
}

/// tract is the CPU target: it must load every fixture and agree with ORT.
#[test]
fn tract_agrees_with_ort_on_fixtures() {
    for f in fixtures() {
        let model = load(&f);
        let inputs = inputs_for(&model, 11);
        let reference = runtime::load(Engine::Ort, &model, &inputs, 1).unwrap().run(&inputs).unwrap();
        let mut tract = runtime::load(Engine::Tract, &model, &inputs, 1).unwrap();
        assert_eq!(tract.name(), "tract");
        let got = tract.run(&inputs).unwrap();
        for ((n, r), (_, t)) in reference.iter().zip(&got) {
            assert_eq!(r.shape, t.shape, "{}: {n}", f.display());
            let e = rel_l2(r, t);
            assert!(e < 1e-4, "{}: output {n} rel L2 {e:e} between ORT and tract", f.display());
        }
        // On a thread pool tract splits the same products differently: only summation order
        // may change.
        let pooled = runtime::load(Engine::Tract, &model, &inputs, 3).unwrap().run(&inputs).unwrap();
        for ((n, a), (_, b)) in got.iter().zip(&pooled) {
            let e = rel_l2(a, b);
            assert!(e < 1e-5, "{}: output {n} rel L2 {e:e} between tract on 1 and 3 threads", f.display());
        }
    }
}

/// Intermediate values can be observed on both runtimes.
#[test]
fn intermediate_values_can_be_exposed() {
    let f = repo().join("models/fixtures/pdinet_v5_const_op17_fold.onnx");
    let model = load(&f);
    let g = model.graph.as_ref().unwrap();
    let clip = g.node.iter().find(|n| n.op_type == "Clip").unwrap().output[0].clone();
    let exposed = pdi_compile::onnx::edit::expose_outputs(&model, std::slice::from_ref(&clip));
    let inputs = inputs_for(&model, 3);
    for engine in [Engine::Ort, Engine::Tract] {
        let out = runtime::load(engine, &exposed, &inputs, 1).unwrap().run(&inputs).unwrap();
        let (name, gate) = out.last().unwrap();
        assert_eq!(name, &clip);
        let v = gate.as_f32().unwrap();
        assert!(v.iter().all(|&x| (0.0..=1.0).contains(&x)), "{engine:?}: a gate leaves [0, 1]");
    }
}
