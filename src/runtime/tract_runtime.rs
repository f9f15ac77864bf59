//! tract (the CPU deployment target), with shapes fixed from the first inputs it is given.

use super::{NamedTensors, Runtime};
use crate::onnx::proto::{GraphProto, ModelProto};
use crate::tensor::{Tensor, TensorData};
use anyhow::{anyhow, bail, Result};
use prost::Message;
use std::sync::{Arc, Mutex};
use tract_linalg::multithread::Executor;
use tract_onnx::prelude::{tvec, Datum, DatumType, Framework, InferenceFact, InferenceModelExt, IntoTValue, RunOptions, Tensor as TractTensor, TypedModel, TypedRunnableModel};

pub struct TractRuntime {
    plan: Arc<TypedRunnableModel>,
    input_names: Vec<String>,
    output_names: Vec<String>,
}

impl TractRuntime {
    /// `inputs` gives the concrete type and shape of every graph input (tract optimizes for
    /// them); `threads` sizes the pool its matrix products and element-wise ops run on.
    pub fn new(model: &ModelProto, inputs: &[(String, Tensor)], threads: usize) -> Result<TractRuntime> {
        let (typed, input_names, output_names) = typed_model(model, inputs)?;
        Self::from_typed(typed, input_names, output_names, threads)
    }

    /// A runtime for a model tract already holds (an NNEF archive, say).
    pub fn from_typed(typed: TypedModel, input_names: Vec<String>, output_names: Vec<String>, threads: usize) -> Result<TractRuntime> {
        let options = RunOptions { executor: Some(executor(threads)), ..Default::default() };
        let plan = typed.into_optimized().and_then(|m| m.into_runnable_with_options(&options)).map_err(|e| anyhow!("tract cannot optimize the model: {e:#}"))?;
        Ok(TractRuntime { plan, input_names, output_names })
    }
}

/// One rayon pool per thread count for the whole process: building a pool per session would
/// spawn threads for every verify or bench variant.
fn executor(threads: usize) -> Executor {
    static POOLS: Mutex<Vec<(usize, Executor)>> = Mutex::new(Vec::new());
    if threads <= 1 {
        return Executor::SingleThread;
    }
    let mut pools = POOLS.lock().unwrap_or_else(|e| e.into_inner());
    if let Some((_, e)) = pools.iter().find(|(n, _)| *n == threads) {
        return e.clone();
    }
    let e = Executor::multithread_with_name(threads, "pdi-tract");
    pools.push((threads, e.clone()));
    e
}

/// `model` as tract is given it ([`make_tract_ready`]), borrowed when nothing changes.
pub fn tract_ready(model: &ModelProto) -> Result<std::borrow::Cow<'_, ModelProto>> {
    let graph = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    if !crate::ir::rewrite::split_depthwise::any_to_split(graph) && !crate::ir::rewrite::any_narrow_form(graph) && !crate::ir::rewrite::space_to_depth::any_rewritten(graph) {
        return Ok(std::borrow::Cow::Borrowed(model));
    }
    let mut ready = model.clone();
    make_tract_ready(ready.graph.as_mut().expect("checked above"))?;
    Ok(std::borrow::Cow::Owned(ready))
}

/// Rewrites `g` into the form tract is given: `narrow-convs-nchw`'s 3-D convolutions back in
/// 2-D (the same sums), which tract ran slower (1.15x on the pruned width-0.25 v5 at
/// 640x480), and its pinned biases constant again (a layout hint for ONNX Runtime alone),
/// `space-to-depth`'s float blocks back at full resolution (tract's convolutions
/// follow their multiplications: 2.1x slower on blocks), and depthwise convolutions wider
/// than tract's SIMD kernel takes split into bands (`split-wide-depthwise`; the same sums in
/// another order), since past 128 taps tract runs them as scalar loops. Returns the depthwise
/// convolutions split and those left.
pub fn make_tract_ready(g: &mut GraphProto) -> Result<(Vec<serde_json::Value>, Vec<serde_json::Value>)> {
    crate::ir::rewrite::lower_narrow_forms(g)?;
    crate::ir::rewrite::space_to_depth::lower_all(g)?;
    crate::ir::rewrite::split_depthwise::split_all(g)
}

/// The decluttered typed model of `model` (made [`tract_ready`]) with its inputs fixed to the
/// shapes of `inputs`, and its input and output names.
pub fn typed_model(model: &ModelProto, inputs: &[(String, Tensor)]) -> Result<(TypedModel, Vec<String>, Vec<String>)> {
    let model = tract_ready(model)?;
    let graph = model.graph.as_ref().ok_or_else(|| anyhow!("model has no graph"))?;
    let inits: std::collections::HashSet<&str> = graph.initializer.iter().map(|t| t.name.as_str()).collect();
    let input_names: Vec<String> = graph.input.iter().map(|v| v.name.clone()).filter(|n| !inits.contains(n.as_str())).collect();
    let output_names: Vec<String> = graph.output.iter().map(|v| v.name.clone()).collect();
    let bytes = model.encode_to_vec();
    let mut inference = tract_onnx::onnx().model_for_read(&mut &bytes[..]).map_err(|e| anyhow!("tract cannot load the model: {e:#}"))?;
    for (i, name) in input_names.iter().enumerate() {
        let t = lookup(inputs, name)?;
        let fact = InferenceFact::dt_shape(datum_type(t)?, t.shape.clone());
        inference.set_input_fact(i, fact).map_err(|e| anyhow!("tract: input {name}: {e:#}"))?;
    }
    let typed = inference.into_typed().and_then(|m| m.into_decluttered()).map_err(|e| anyhow!("tract cannot type the model: {e:#}"))?;
    Ok((typed, input_names, output_names))
}

impl TractRuntime {
    /// The optimized plan (the profiler runs it node by node).
    pub fn plan(&self) -> &Arc<TypedRunnableModel> {
        &self.plan
    }

    /// `inputs` as the plan takes them, in its input order.
    pub fn input_values(&self, inputs: &[(String, Tensor)]) -> Result<tract_onnx::prelude::TVec<tract_onnx::prelude::TValue>> {
        let mut values = tvec![];
        for name in &self.input_names {
            values.push(to_tract(lookup(inputs, name)?)?.into_tvalue());
        }
        Ok(values)
    }
}

impl Runtime for TractRuntime {
    fn name(&self) -> &'static str {
        "tract"
    }

    fn run(&mut self, inputs: &[(String, Tensor)]) -> Result<NamedTensors> {
        let values = self.input_values(inputs)?;
        let out = self.plan.run(values).map_err(|e| anyhow!("tract failed: {e:#}"))?;
        self.output_names.iter().cloned().zip(out.iter().map(|v| from_tract(v))).map(|(n, t)| Ok((n, t?))).collect()
    }
}

fn lookup<'a>(inputs: &'a [(String, Tensor)], name: &str) -> Result<&'a Tensor> {
    inputs.iter().find(|(n, _)| n == name).map(|(_, t)| t).ok_or_else(|| anyhow!("no value given for input {name}"))
}

fn datum_type(t: &Tensor) -> Result<DatumType> {
    Ok(match &t.data {
        TensorData::F32(_) => f32::datum_type(),
        TensorData::F64(_) => f64::datum_type(),
        TensorData::F16(_) => half::f16::datum_type(),
        TensorData::I8(_) => i8::datum_type(),
        TensorData::I16(_) => i16::datum_type(),
        TensorData::I32(_) => i32::datum_type(),
        TensorData::I64(_) => i64::datum_type(),
        TensorData::U8(_) => u8::datum_type(),
        TensorData::U16(_) => u16::datum_type(),
        TensorData::U32(_) => u32::datum_type(),
        TensorData::U64(_) => u64::datum_type(),
        TensorData::Bool(_) => bool::datum_type(),
        other => bail!("tract runtime does not take {:?} inputs", other.dtype()),
    })
}

fn to_tract(t: &Tensor) -> Result<TractTensor> {
    let s = &t.shape;
    let r = match &t.data {
        TensorData::F32(v) => TractTensor::from_shape(s, v),
        TensorData::F64(v) => TractTensor::from_shape(s, v),
        TensorData::F16(v) => TractTensor::from_shape(s, v),
        TensorData::I8(v) => TractTensor::from_shape(s, v),
        TensorData::I16(v) => TractTensor::from_shape(s, v),
        TensorData::I32(v) => TractTensor::from_shape(s, v),
        TensorData::I64(v) => TractTensor::from_shape(s, v),
        TensorData::U8(v) => TractTensor::from_shape(s, v),
        TensorData::U16(v) => TractTensor::from_shape(s, v),
        TensorData::U32(v) => TractTensor::from_shape(s, v),
        TensorData::U64(v) => TractTensor::from_shape(s, v),
        TensorData::Bool(v) => TractTensor::from_shape(s, v),
        other => bail!("tract runtime does not take {:?} inputs", other.dtype()),
    };
    r.map_err(|e| anyhow!("{e:#}"))
}

fn from_tract(v: &TractTensor) -> Result<Tensor> {
    let shape = v.shape().to_vec();
    let view = v.try_as_plain_ram().map_err(|e| anyhow!("{e:#}"))?;
    macro_rules! grab {
        ($t:ty, $variant:ident) => {
            TensorData::$variant(view.as_slice::<$t>().map_err(|e| anyhow!("{e:#}"))?.to_vec())
        };
    }
    let dt = v.datum_type();
    let data = if dt == f32::datum_type() {
        grab!(f32, F32)
    } else if dt == f64::datum_type() {
        grab!(f64, F64)
    } else if dt == half::f16::datum_type() {
        grab!(half::f16, F16)
    } else if dt == i64::datum_type() {
        grab!(i64, I64)
    } else if dt == i32::datum_type() {
        grab!(i32, I32)
    } else if dt == i16::datum_type() {
        grab!(i16, I16)
    } else if dt == i8::datum_type() {
        grab!(i8, I8)
    } else if dt == u8::datum_type() {
        grab!(u8, U8)
    } else if dt == u16::datum_type() {
        grab!(u16, U16)
    } else if dt == u32::datum_type() {
        grab!(u32, U32)
    } else if dt == u64::datum_type() {
        grab!(u64, U64)
    } else if dt == bool::datum_type() {
        grab!(bool, Bool)
    } else {
        bail!("tract produced a {dt:?} output, which is not supported")
    };
    Ok(Tensor::new(shape, data))
}
