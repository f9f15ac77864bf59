//! The ONNX backend node tests shipped inside the `onnx` Python package, through our I/O:
//! load -> save -> run the saved file in ORT -> compare with the test's expected outputs.
//!
//! Every case is accounted for in `target/onnx-node-tests.txt`: passed, or why not. Cases
//! that ORT cannot run even from the original file are ORT's limits, listed with ORT's
//! message; anything our round trip or IR breaks fails this test.

use crate::common;
use pdi_compile::onnx::proto::{ModelProto, TensorProto, TypeValue};
use pdi_compile::onnx::tensor_proto::to_tensor;
use pdi_compile::runtime::ort_runtime::OrtRuntime;
use pdi_compile::runtime::Runtime;
use pdi_compile::tensor::Tensor;
use prost::Message;
use std::fmt::Write;
use std::path::{Path, PathBuf};

/// The ONNX backend's default tolerances (onnx/backend/test/runner).
const RTOL: f64 = 1e-3;
const ATOL: f64 = 1e-7;

enum Outcome {
    Pass,
    /// ORT cannot run the original model (its limits, not ours).
    OrtCannotRun(String),
    /// ORT runs it but disagrees with the expected outputs, identically before and after our round trip.
    OrtMismatch(String),
    /// The harness's tensor interface does not carry sequences, maps or optionals.
    NonTensorIo,
    /// Test data in an element type our `Tensor` does not carry (int4, float8, ...).
    HarnessDtype(String),
    /// Our round trip or IR broke something.
    Fail(String),
}

fn node_test_dir() -> PathBuf {
    let dir = std::env::var_os("PDI_ONNX_NODE_TESTS")
        .map(PathBuf::from)
        .expect("PDI_ONNX_NODE_TESTS is not set: run the suite with scripts/test, which installs the onnx package");
    assert!(dir.is_dir(), "PDI_ONNX_NODE_TESTS={} is not a folder", dir.display());
    dir
}

fn read_pbs(dir: &Path, prefix: &str) -> Vec<TensorProto> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.file_name().unwrap().to_str().unwrap().starts_with(prefix))
        .collect();
    files.sort_by_key(|p| p.file_stem().unwrap().to_str().unwrap().rsplit('_').next().unwrap().parse::<usize>().unwrap());
    files.iter().map(|f| TensorProto::decode(&*std::fs::read(f).unwrap()).unwrap()).collect()
}

fn all_tensor_io(m: &ModelProto) -> bool {
    let g = m.graph.as_ref().unwrap();
    g.input.iter().chain(&g.output).all(|v| matches!(v.r#type.as_ref().and_then(|t| t.value.as_ref()), Some(TypeValue::TensorType(_))))
}

fn close(expected: &Tensor, got: &Tensor) -> Result<(), String> {
    if expected.shape != got.shape || expected.dtype() != got.dtype() {
        return Err(format!("shape/type {:?} {:?} vs expected {:?} {:?}", got.shape, got.dtype(), expected.shape, expected.dtype()));
    }
    if let (pdi_compile::tensor::TensorData::Str(a), pdi_compile::tensor::TensorData::Str(b)) = (&expected.data, &got.data) {
        return if a == b { Ok(()) } else { Err("strings differ".into()) };
    }
    for (i, (e, g)) in expected.data.to_f64().iter().zip(got.data.to_f64()).enumerate() {
        let ok = (e.is_nan() && g.is_nan()) || e == &g || (e - g).abs() <= ATOL + RTOL * e.abs();
        if !ok {
            return Err(format!("element {i}: {g} vs expected {e}"));
        }
    }
    Ok(())
}

fn run_case(dir: &Path) -> Outcome {
    let bytes = std::fs::read(dir.join("model.onnx")).unwrap();
    let loaded = match pdi_compile::onnx::load_bytes(&bytes, Some(dir)) {
        Ok(l) => l,
        Err(e) => return Outcome::Fail(format!("our loader: {e:#}")),
    };
    let model = loaded.model;
    if let Err(e) = pdi_compile::ir::Graph::build(model.graph.as_ref().unwrap()).map(|g| pdi_compile::ir::infer(&g)) {
        return Outcome::Fail(format!("our IR rejects a valid model: {e:#}"));
    }
    let reencoded = model.encode_to_vec();
    let saved = match pdi_compile::onnx::load_bytes(&reencoded, None) {
        Ok(l) => l.model,
        Err(e) => return Outcome::Fail(format!("reloading the saved file: {e:#}")),
    };
    // Compared as bytes: float attributes may hold NaN, which `==` never equates.
    if saved.encode_to_vec() != reencoded {
        return Outcome::Fail("saved model decodes differently".into());
    }
    if !all_tensor_io(&model) {
        return Outcome::NonTensorIo;
    }
    let data = dir.join("test_data_set_0");
    let g = model.graph.as_ref().unwrap();
    let inits: Vec<&str> = g.initializer.iter().map(|t| t.name.as_str()).collect();
    let names: Vec<String> = g.input.iter().filter(|v| !inits.contains(&v.name.as_str())).map(|v| v.name.clone()).collect();
    let mut inputs = Vec::new();
    for (name, pb) in names.iter().zip(read_pbs(&data, "input_")) {
        match to_tensor(&pb) {
            Ok(t) => inputs.push((name.clone(), t)),
            Err(e) => return Outcome::HarnessDtype(format!("{e:#}")),
        }
    }
    let expected: Vec<Tensor> = match read_pbs(&data, "output_").iter().map(to_tensor).collect() {
        Ok(v) => v,
        Err(e) => return Outcome::HarnessDtype(format!("{e:#}")),
    };
    let run = |m: &ModelProto| -> Result<Vec<Tensor>, String> {
        let mut rt = OrtRuntime::with_options(m, ort::session::builder::GraphOptimizationLevel::Level3, 1).map_err(|e| format!("{e:#}"))?;
        rt.run(&inputs).map(|o| o.into_iter().map(|(_, t)| t).collect()).map_err(|e| format!("{e:#}"))
    };
    let original = match run(&model) {
        Ok(o) => o,
        Err(e) => return Outcome::OrtCannotRun(e),
    };
    let after = match run(&saved) {
        Ok(o) => o,
        Err(e) => return Outcome::Fail(format!("ORT runs the original but not the saved file: {e}")),
    };
    if original.len() != after.len() || original.iter().zip(&after).any(|(a, b)| !a.bit_identical(b)) {
        return Outcome::Fail("ORT outputs of the saved file differ from the original's".into());
    }
    for (i, (e, g)) in expected.iter().zip(&after).enumerate() {
        if let Err(msg) = close(e, g) {
            return Outcome::OrtMismatch(format!("output {i}: {msg}"));
        }
    }
    Outcome::Pass
}

#[test]
fn onnx_backend_node_tests_round_trip() {
    let root = node_test_dir();
    let mut cases: Vec<PathBuf> = std::fs::read_dir(&root).unwrap().map(|e| e.unwrap().path()).filter(|p| p.join("model.onnx").is_file()).collect();
    cases.sort();
    assert!(cases.len() > 1000, "only {} node tests found in {}", cases.len(), root.display());
    let (mut pass, mut ort_cannot, mut mismatch, mut non_tensor, mut harness, mut failures) = (0, Vec::new(), Vec::new(), 0, 0, Vec::new());
    let mut listing = String::new();
    for c in &cases {
        let name = c.file_name().unwrap().to_string_lossy().into_owned();
        let line = match run_case(c) {
            Outcome::Pass => { pass += 1; continue; }
            Outcome::OrtCannotRun(r) => { ort_cannot.push(name.clone()); format!("ort-cannot-run\t{name}\t{r}") }
            Outcome::OrtMismatch(r) => { mismatch.push(name.clone()); format!("ort-mismatch\t{name}\t{r}") }
            Outcome::HarnessDtype(r) => { harness += 1; format!("harness-dtype\t{name}\t{r}: round trip checked, not run") }
            Outcome::NonTensorIo => { non_tensor += 1; format!("non-tensor-io\t{name}\tsequence/map/optional inputs or outputs: round trip checked, not run") }
            Outcome::Fail(r) => { failures.push(format!("{name}: {r}")); format!("FAIL\t{name}\t{r}") }
        };
        let _ = writeln!(listing, "{}", line.replace('\n', " "));
    }
    let summary = format!(
        "ONNX node tests: {} cases, {pass} passed, {} ORT cannot run, {} ORT mismatches, {non_tensor} non-tensor I/O, {harness} exotic dtypes, {} failed",
        cases.len(), ort_cannot.len(), mismatch.len(), failures.len()
    );
    let report = common::repo().join("target/onnx-node-tests.txt");
    std::fs::write(&report, format!("# {summary}\n# category\tcase\treason\n{listing}")).unwrap();
    println!("{summary}\n(details: {})", report.display());
    assert!(failures.is_empty(), "{} cases broken by our round trip:\n{}", failures.len(), failures.join("\n"));
    assert!(pass * 10 >= cases.len() * 8, "{summary}: under 80% pass");
}
