//! ONNX Runtime (the reference) through the `ort` crate.

use super::{NamedTensors, Runtime};
use crate::onnx::proto::ModelProto;
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Context, Result};
use ort::session::{builder::GraphOptimizationLevel, builder::SessionBuilder, Session};
use ort::value::{DynValue, Tensor as OrtTensor, TensorElementType, ValueType};
use prost::Message;

pub struct OrtRuntime {
    session: Session,
}

/// Whether ONNX Runtime's intra-op threads spin between parallel sections (its default, the
/// lowest latency). `PDI_ORT_SPIN=0` makes them sleep: where several processes share the
/// cores (the test suite's tests side by side), a spinning pool takes them from the others.
fn spinning() -> bool {
    std::env::var_os("PDI_ORT_SPIN").is_none_or(|v| v != "0")
}

/// ONNX Runtime's error while building a session, as every session here reports it.
fn rejected(e: ort::Error) -> anyhow::Error {
    anyhow!("ONNX Runtime rejected the model: {e}")
}

/// A session builder at `level` on `threads` intra-op threads, spinning as [`spinning`] says:
/// what every session here starts from.
fn builder(level: GraphOptimizationLevel, threads: usize) -> Result<SessionBuilder> {
    let env = super::ort_lib::environment()?;
    Session::builder(env)
        .and_then(|b| b.with_optimization_level(level).map_err(Into::into))
        .and_then(|b| b.with_intra_threads(threads).map_err(Into::into))
        .and_then(|b| if spinning() { Ok(b) } else { b.with_intra_op_spinning(false).map_err(Into::into) })
        .map_err(rejected)
}

impl OrtRuntime {
    pub fn new(model: &ModelProto) -> Result<OrtRuntime> {
        Self::with_options(model, GraphOptimizationLevel::Level3, 1)
    }

    pub fn with_options(model: &ModelProto, level: GraphOptimizationLevel, threads: usize) -> Result<OrtRuntime> {
        Self::build(model, level, threads, None)
    }

    /// A session that records ORT's profile under `prefix` until [`Self::end_profiling`].
    pub fn profiled(model: &ModelProto, threads: usize, prefix: &std::path::Path) -> Result<OrtRuntime> {
        Self::build(model, GraphOptimizationLevel::Level3, threads, Some(prefix))
    }

    fn build(model: &ModelProto, level: GraphOptimizationLevel, threads: usize, profile: Option<&std::path::Path>) -> Result<OrtRuntime> {
        let mut b = builder(level, threads)?;
        if let Some(p) = profile {
            b = b.with_profiling(p).map_err(|e| rejected(e.into()))?;
        }
        let session = b.commit_from_memory(&model.encode_to_vec()).map_err(rejected)?;
        Ok(OrtRuntime { session })
    }

    /// Ends a [`Self::profiled`] session's profile; returns the file it wrote.
    pub fn end_profiling(&mut self) -> Result<String> {
        self.session.end_profiling().map_err(|e| anyhow!("ONNX Runtime could not write its profile: {e}"))
    }

    /// The graph ONNX Runtime actually runs for `model` after its optimizations (fusions
    /// such as DQ -> Conv -> Q into QLinearConv), as op type -> count.
    pub fn optimized_ops(model: &ModelProto) -> Result<std::collections::BTreeMap<String, usize>> {
        static SEQ: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
        let path = std::env::temp_dir().join(format!("pdi-compile-optimized-{}-{}.onnx", std::process::id(), SEQ.fetch_add(1, std::sync::atomic::Ordering::Relaxed)));
        let bytes = model.encode_to_vec();
        let built = builder(GraphOptimizationLevel::Level3, 1)?
            .with_optimized_model_path(&path)
            .map_err(Into::into)
            .and_then(|mut b| b.commit_from_memory(&bytes))
            .map_err(rejected);
        let counted = built.and_then(|_| {
            let m = crate::onnx::io::load(&path)?.model;
            let mut ops = std::collections::BTreeMap::new();
            for n in m.graph.iter().flat_map(|g| &g.node) {
                *ops.entry(n.op_type.clone()).or_insert(0) += 1;
            }
            Ok(ops)
        });
        let _ = std::fs::remove_file(&path);
        counted
    }

    pub fn output_names(&self) -> Vec<String> {
        self.session.outputs().iter().map(|o| o.name().to_string()).collect()
    }
}

impl OrtRuntime {
    /// Runs once and shows the float32 outputs to `f` in place, all at once (no copy:
    /// calibration reads hundreds of megabytes of activations per 640x480 frame).
    pub fn visit_f32<R>(&mut self, inputs: &[(String, Tensor)], f: impl FnOnce(&[(&str, &[f32])]) -> R) -> Result<R> {
        let values = ort_inputs(inputs)?;
        let names = self.output_names();
        let outputs = self.session.run(lend(&values)).map_err(|e| anyhow!("ONNX Runtime failed: {e}"))?;
        let mut seen: Vec<(&str, &[f32])> = Vec::new();
        for n in &names {
            if let Some(Ok((_, data))) = outputs.get(n).map(|v| v.try_extract_tensor::<f32>()) {
                seen.push((n.as_str(), data));
            }
        }
        Ok(f(&seen))
    }
}

impl Runtime for OrtRuntime {
    fn name(&self) -> &'static str {
        "ort"
    }

    fn run(&mut self, inputs: &[(String, Tensor)]) -> Result<NamedTensors> {
        let values = ort_inputs(inputs)?;
        let names = self.output_names();
        let outputs = self.session.run(lend(&values)).map_err(|e| anyhow!("ONNX Runtime failed: {e}"))?;
        names
            .into_iter()
            .map(|n| {
                let v = outputs.get(&n).ok_or_else(|| anyhow!("ONNX Runtime returned no output {n}"))?;
                let t = from_ort(v).with_context(|| format!("output {n}"))?;
                Ok((n, t))
            })
            .collect()
    }
}

fn ort_inputs(inputs: &[(String, Tensor)]) -> Result<Vec<(String, DynValue)>> {
    inputs.iter().map(|(name, t)| Ok((name.clone(), to_ort(t).with_context(|| format!("input {name}"))?))).collect()
}

/// Inputs lent to a run, not given: an output that is a graph input (a halo's fit exposes the
/// image) is ORT's view of the input's buffer, which must outlive the outputs.
fn lend(values: &[(String, DynValue)]) -> Vec<(&str, &DynValue)> {
    values.iter().map(|(n, v)| (n.as_str(), v)).collect()
}

fn to_ort(t: &Tensor) -> Result<DynValue> {
    let shape: Vec<i64> = t.shape.iter().map(|&d| d as i64).collect();
    macro_rules! prim {
        ($v:expr) => {
            OrtTensor::from_array((shape.clone(), $v.clone())).map(|x| x.into_dyn())
        };
    }
    let v = match &t.data {
        TensorData::F32(v) => prim!(v),
        TensorData::F64(v) => prim!(v),
        TensorData::F16(v) => prim!(v),
        TensorData::Bf16(v) => prim!(v),
        TensorData::I8(v) => prim!(v),
        TensorData::I16(v) => prim!(v),
        TensorData::I32(v) => prim!(v),
        TensorData::I64(v) => prim!(v),
        TensorData::U8(v) => prim!(v),
        TensorData::U16(v) => prim!(v),
        TensorData::U32(v) => prim!(v),
        TensorData::U64(v) => prim!(v),
        TensorData::Bool(v) => prim!(v),
        TensorData::Str(v) => OrtTensor::from_string_array((shape.clone(), v.as_slice())).map(|x| x.into_dyn()),
    };
    v.map_err(|e| anyhow!("cannot build an ONNX Runtime tensor: {e}"))
}

fn from_ort(v: &DynValue) -> Result<Tensor> {
    let (ty, shape) = match v.dtype() {
        ValueType::Tensor { ty, shape, .. } => (*ty, shape),
        other => bail!("non-tensor value ({other:?}) is not supported"),
    };
    // An empty tensor has no data pointer for ort to make a slice of (debug builds abort).
    let empty = shape.contains(&0);
    macro_rules! prim {
        ($t:ty, $variant:ident) => {{
            if empty {
                Tensor::new(dims(shape), TensorData::$variant(Vec::new()))
            } else {
                let (shape, data) = v.try_extract_tensor::<$t>().map_err(|e| anyhow!("{e}"))?;
                Tensor::new(dims(shape), TensorData::$variant(data.to_vec()))
            }
        }};
    }
    Ok(match ty {
        TensorElementType::Float32 => prim!(f32, F32),
        TensorElementType::Float64 => prim!(f64, F64),
        TensorElementType::Float16 => prim!(half::f16, F16),
        TensorElementType::Bfloat16 => prim!(half::bf16, Bf16),
        TensorElementType::Int8 => prim!(i8, I8),
        TensorElementType::Int16 => prim!(i16, I16),
        TensorElementType::Int32 => prim!(i32, I32),
        TensorElementType::Int64 => prim!(i64, I64),
        TensorElementType::Uint8 => prim!(u8, U8),
        TensorElementType::Uint16 => prim!(u16, U16),
        TensorElementType::Uint32 => prim!(u32, U32),
        TensorElementType::Uint64 => prim!(u64, U64),
        TensorElementType::Bool => prim!(bool, Bool),
        TensorElementType::String => {
            let (shape, data) = v.try_extract_strings().map_err(|e| anyhow!("{e}"))?;
            Tensor::new(dims(shape), TensorData::Str(data))
        }
        other => bail!("element type {other:?} is not supported"),
    })
}

fn dims(shape: &ort::value::Shape) -> Vec<usize> {
    shape.iter().map(|&d| d.max(0) as usize).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::onnx::edit::tensor_value_info;
    use crate::onnx::proto::{GraphProto, NodeProto, OperatorSetIdProto};
    use crate::tensor::DType;

    /// An output that is the graph's own input comes back as the input, run after run. ORT
    /// hands it out as a view of the input's buffer; before inputs were lent, that buffer was
    /// freed before the outputs were read (4 MiB: the allocator unmaps it, so a read crashes).
    #[test]
    fn an_input_exposed_as_an_output_reads_back_intact() {
        let n = 1 << 20;
        let graph = GraphProto {
            node: vec![NodeProto { op_type: "Relu".into(), input: vec!["x".into()], output: vec!["y".into()], ..Default::default() }],
            input: vec![tensor_value_info("x", DType::F32, &[1, n])],
            output: vec![tensor_value_info("x", DType::F32, &[1, n]), tensor_value_info("y", DType::F32, &[1, n])],
            ..Default::default()
        };
        let model = ModelProto { ir_version: 8, opset_import: vec![OperatorSetIdProto { domain: String::new(), version: 17 }], graph: Some(graph), ..Default::default() };
        let mut rt = OrtRuntime::new(&model).unwrap();
        for run in 0..4 {
            let v: Vec<f32> = (0..n).map(|i| ((i + run * 7) % 13) as f32 - 6.0).collect();
            let feed = vec![("x".to_string(), Tensor::f32(vec![1, n], v.clone()))];
            let seen = rt.visit_f32(&feed, |seen| seen.iter().map(|(name, d)| (name.to_string(), d.to_vec())).collect::<Vec<_>>()).unwrap();
            let x = &seen.iter().find(|(name, _)| name == "x").expect("x is an output").1;
            assert!(x == &v, "run {run}: the input read back changed");
            let out = rt.run(&feed).unwrap();
            assert_eq!(out.iter().find(|(name, _)| name == "x").unwrap().1.as_f32().unwrap(), &v[..], "run {run}: Runtime::run");
        }
    }
}
