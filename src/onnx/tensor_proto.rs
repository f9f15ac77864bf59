//! `TensorProto` <-> [`Tensor`]: raw_data and every typed field, with sizes checked first.
//!
//! Untrusted files can claim any dims; nothing is allocated from a claimed size before it is
//! checked against the bytes actually present.

use crate::onnx::proto::TensorProto;
use crate::tensor::{onnx_dtype_name, DType, Tensor, TensorData};
use anyhow::{bail, Result};
use half::{bf16, f16};

/// Element count of `dims`, rejecting negative dimensions and overflow.
pub fn element_count(dims: &[i64]) -> Result<usize> {
    let mut n: usize = 1;
    for &d in dims {
        if d < 0 {
            bail!("negative dimension {d} in shape {dims:?}");
        }
        n = n.checked_mul(d as usize).ok_or_else(|| anyhow::anyhow!("shape {dims:?} has more elements than memory can hold"))?;
    }
    Ok(n)
}

pub fn to_tensor(t: &TensorProto) -> Result<Tensor> {
    let dtype = DType::from_onnx(t.data_type)
        .ok_or_else(|| anyhow::anyhow!("tensor '{}' has data type {} ({}), which is not supported", t.name, t.data_type, onnx_dtype_name(t.data_type)))?;
    if t.data_location == crate::onnx::proto::DATA_LOCATION_EXTERNAL {
        bail!("tensor '{}' still points to external data; load the model with its folder", t.name);
    }
    let n = element_count(&t.dims).map_err(|e| anyhow::anyhow!("tensor '{}': {e}", t.name))?;
    let shape: Vec<usize> = t.dims.iter().map(|&d| d as usize).collect();
    let data = if !t.raw_data.is_empty() || (n == 0 && dtype != DType::Str) {
        let want = n.saturating_mul(dtype.size_of());
        if dtype == DType::Str || t.raw_data.len() != want {
            bail!("tensor '{}': raw_data holds {} bytes, shape {:?} of {} needs {want}", t.name, t.raw_data.len(), t.dims, onnx_dtype_name(t.data_type));
        }
        TensorData::from_le_bytes(dtype, &t.raw_data)
    } else {
        typed_field(t, dtype)?
    };
    if data.len() != n {
        bail!("tensor '{}': {} values stored, shape {:?} needs {n}", t.name, data.len(), t.dims);
    }
    Ok(Tensor::new(shape, data))
}

/// The typed `*_data` fields, as the ONNX spec assigns them per type.
fn typed_field(t: &TensorProto, dtype: DType) -> Result<TensorData> {
    let i32s = &t.int32_data;
    Ok(match dtype {
        DType::F32 => TensorData::F32(t.float_data.clone()),
        DType::F64 => TensorData::F64(t.double_data.clone()),
        DType::I64 => TensorData::I64(t.int64_data.clone()),
        DType::U32 => TensorData::U32(t.uint64_data.iter().map(|&x| x as u32).collect()),
        DType::U64 => TensorData::U64(t.uint64_data.clone()),
        DType::I32 => TensorData::I32(i32s.clone()),
        DType::I16 => TensorData::I16(i32s.iter().map(|&x| x as i16).collect()),
        DType::I8 => TensorData::I8(i32s.iter().map(|&x| x as i8).collect()),
        DType::U16 => TensorData::U16(i32s.iter().map(|&x| x as u16).collect()),
        DType::U8 => TensorData::U8(i32s.iter().map(|&x| x as u8).collect()),
        DType::Bool => TensorData::Bool(i32s.iter().map(|&x| x != 0).collect()),
        DType::F16 => TensorData::F16(i32s.iter().map(|&x| f16::from_bits(x as u16)).collect()),
        DType::Bf16 => TensorData::Bf16(i32s.iter().map(|&x| bf16::from_bits(x as u16)).collect()),
        DType::Str => TensorData::Str(t.string_data.iter().map(|s| String::from_utf8_lossy(s).into_owned()).collect()),
    })
}

/// A `TensorProto` named `name` holding `t` in `raw_data` (strings in `string_data`).
pub fn from_tensor(name: &str, t: &Tensor) -> TensorProto {
    let mut p = TensorProto {
        name: name.to_string(),
        dims: t.shape.iter().map(|&d| d as i64).collect(),
        data_type: t.dtype().onnx_code(),
        ..Default::default()
    };
    match &t.data {
        TensorData::Str(v) => p.string_data = v.iter().map(|s| s.as_bytes().to_vec()).collect(),
        d => p.raw_data = d.to_le_bytes().unwrap_or_default(),
    }
    p
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn typed_and_raw_fields_decode_alike() {
        let raw = from_tensor("w", &Tensor::new(vec![2, 2], TensorData::I8(vec![-1, 2, -3, 4])));
        let typed = TensorProto { dims: vec![2, 2], data_type: 3, int32_data: vec![-1, 2, -3, 4], ..Default::default() };
        assert_eq!(to_tensor(&raw).unwrap(), to_tensor(&typed).unwrap());
        let h = TensorProto { dims: vec![1], data_type: 10, int32_data: vec![0x3c00], ..Default::default() };
        assert_eq!(to_tensor(&h).unwrap().data, TensorData::F16(vec![f16::ONE]));
    }

    #[test]
    fn claimed_sizes_are_checked_before_use() {
        let huge = TensorProto { dims: vec![1 << 40, 1 << 40], data_type: 1, raw_data: vec![0; 8], ..Default::default() };
        assert!(to_tensor(&huge).is_err());
        let neg = TensorProto { dims: vec![-3], data_type: 1, ..Default::default() };
        assert!(to_tensor(&neg).unwrap_err().to_string().contains("negative"));
        let short = TensorProto { dims: vec![4], data_type: 1, float_data: vec![1.0], ..Default::default() };
        assert!(to_tensor(&short).is_err());
    }
}
