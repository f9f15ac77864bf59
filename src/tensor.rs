//! An owned, typed tensor: the currency between ONNX initializers, runtimes and reports.

use half::{bf16, f16};

/// ONNX `TensorProto.DataType` codes for the element types we carry.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum DType {
    F32,
    U8,
    I8,
    U16,
    I16,
    I32,
    I64,
    Str,
    Bool,
    F16,
    F64,
    U32,
    U64,
    Bf16,
}

impl DType {
    pub fn from_onnx(code: i32) -> Option<DType> {
        Some(match code {
            1 => DType::F32,
            2 => DType::U8,
            3 => DType::I8,
            4 => DType::U16,
            5 => DType::I16,
            6 => DType::I32,
            7 => DType::I64,
            8 => DType::Str,
            9 => DType::Bool,
            10 => DType::F16,
            11 => DType::F64,
            12 => DType::U32,
            13 => DType::U64,
            16 => DType::Bf16,
            _ => return None,
        })
    }

    pub fn onnx_code(self) -> i32 {
        match self {
            DType::F32 => 1,
            DType::U8 => 2,
            DType::I8 => 3,
            DType::U16 => 4,
            DType::I16 => 5,
            DType::I32 => 6,
            DType::I64 => 7,
            DType::Str => 8,
            DType::Bool => 9,
            DType::F16 => 10,
            DType::F64 => 11,
            DType::U32 => 12,
            DType::U64 => 13,
            DType::Bf16 => 16,
        }
    }

    /// Bytes per element in `raw_data` (strings have no raw form).
    pub fn size_of(self) -> usize {
        match self {
            DType::U8 | DType::I8 | DType::Bool => 1,
            DType::U16 | DType::I16 | DType::F16 | DType::Bf16 => 2,
            DType::F32 | DType::I32 | DType::U32 => 4,
            DType::F64 | DType::I64 | DType::U64 => 8,
            DType::Str => 0,
        }
    }

    pub fn is_float(self) -> bool {
        matches!(self, DType::F32 | DType::F16 | DType::F64 | DType::Bf16)
    }
}

/// Name of an ONNX data type code, for messages (also the codes we do not carry).
pub fn onnx_dtype_name(code: i32) -> &'static str {
    const NAMES: [&str; 27] = [
        "undefined", "float", "uint8", "int8", "uint16", "int16", "int32", "int64", "string", "bool",
        "float16", "double", "uint32", "uint64", "complex64", "complex128", "bfloat16",
        "float8e4m3fn", "float8e4m3fnuz", "float8e5m2", "float8e5m2fnuz", "uint4", "int4",
        "float4e2m1", "float8e8m0", "uint2", "int2",
    ];
    usize::try_from(code).ok().and_then(|i| NAMES.get(i)).copied().unwrap_or("unknown")
}

#[derive(Clone, Debug, PartialEq)]
pub enum TensorData {
    F32(Vec<f32>),
    F64(Vec<f64>),
    F16(Vec<f16>),
    Bf16(Vec<bf16>),
    I8(Vec<i8>),
    I16(Vec<i16>),
    I32(Vec<i32>),
    I64(Vec<i64>),
    U8(Vec<u8>),
    U16(Vec<u16>),
    U32(Vec<u32>),
    U64(Vec<u64>),
    Bool(Vec<bool>),
    Str(Vec<String>),
}

/// Applies `$body` to the vector inside any variant.
#[macro_export]
macro_rules! each_data {
    ($data:expr, $v:ident => $body:expr) => {
        match $data {
            $crate::tensor::TensorData::F32($v) => $body,
            $crate::tensor::TensorData::F64($v) => $body,
            $crate::tensor::TensorData::F16($v) => $body,
            $crate::tensor::TensorData::Bf16($v) => $body,
            $crate::tensor::TensorData::I8($v) => $body,
            $crate::tensor::TensorData::I16($v) => $body,
            $crate::tensor::TensorData::I32($v) => $body,
            $crate::tensor::TensorData::I64($v) => $body,
            $crate::tensor::TensorData::U8($v) => $body,
            $crate::tensor::TensorData::U16($v) => $body,
            $crate::tensor::TensorData::U32($v) => $body,
            $crate::tensor::TensorData::U64($v) => $body,
            $crate::tensor::TensorData::Bool($v) => $body,
            $crate::tensor::TensorData::Str($v) => $body,
        }
    };
}

impl TensorData {
    pub fn dtype(&self) -> DType {
        match self {
            TensorData::F32(_) => DType::F32,
            TensorData::F64(_) => DType::F64,
            TensorData::F16(_) => DType::F16,
            TensorData::Bf16(_) => DType::Bf16,
            TensorData::I8(_) => DType::I8,
            TensorData::I16(_) => DType::I16,
            TensorData::I32(_) => DType::I32,
            TensorData::I64(_) => DType::I64,
            TensorData::U8(_) => DType::U8,
            TensorData::U16(_) => DType::U16,
            TensorData::U32(_) => DType::U32,
            TensorData::U64(_) => DType::U64,
            TensorData::Bool(_) => DType::Bool,
            TensorData::Str(_) => DType::Str,
        }
    }

    pub fn len(&self) -> usize {
        each_data!(self, v => v.len())
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Little-endian bytes as ONNX `raw_data` stores them (`None` for strings).
    pub fn to_le_bytes(&self) -> Option<Vec<u8>> {
        fn cat<T: Copy, const N: usize>(v: &[T], f: impl Fn(T) -> [u8; N]) -> Vec<u8> {
            v.iter().flat_map(|&x| f(x)).collect()
        }
        Some(match self {
            TensorData::F32(v) => cat(v, f32::to_le_bytes),
            TensorData::F64(v) => cat(v, f64::to_le_bytes),
            TensorData::F16(v) => cat(v, f16::to_le_bytes),
            TensorData::Bf16(v) => cat(v, bf16::to_le_bytes),
            TensorData::I8(v) => cat(v, i8::to_le_bytes),
            TensorData::I16(v) => cat(v, i16::to_le_bytes),
            TensorData::I32(v) => cat(v, i32::to_le_bytes),
            TensorData::I64(v) => cat(v, i64::to_le_bytes),
            TensorData::U8(v) => v.clone(),
            TensorData::U16(v) => cat(v, u16::to_le_bytes),
            TensorData::U32(v) => cat(v, u32::to_le_bytes),
            TensorData::U64(v) => cat(v, u64::to_le_bytes),
            TensorData::Bool(v) => v.iter().map(|&b| b as u8).collect(),
            TensorData::Str(_) => return None,
        })
    }

    /// Decodes little-endian `raw_data`; the caller has checked the length.
    pub fn from_le_bytes(dtype: DType, b: &[u8]) -> TensorData {
        fn conv<T, const N: usize>(b: &[u8], f: impl Fn([u8; N]) -> T) -> Vec<T> {
            b.chunks_exact(N).map(|c| f(c.try_into().expect("chunk of N bytes"))).collect()
        }
        match dtype {
            DType::F32 => TensorData::F32(conv(b, f32::from_le_bytes)),
            DType::F64 => TensorData::F64(conv(b, f64::from_le_bytes)),
            DType::F16 => TensorData::F16(conv(b, f16::from_le_bytes)),
            DType::Bf16 => TensorData::Bf16(conv(b, bf16::from_le_bytes)),
            DType::I8 => TensorData::I8(conv(b, i8::from_le_bytes)),
            DType::I16 => TensorData::I16(conv(b, i16::from_le_bytes)),
            DType::I32 => TensorData::I32(conv(b, i32::from_le_bytes)),
            DType::I64 => TensorData::I64(conv(b, i64::from_le_bytes)),
            DType::U8 => TensorData::U8(b.to_vec()),
            DType::U16 => TensorData::U16(conv(b, u16::from_le_bytes)),
            DType::U32 => TensorData::U32(conv(b, u32::from_le_bytes)),
            DType::U64 => TensorData::U64(conv(b, u64::from_le_bytes)),
            DType::Bool => TensorData::Bool(b.iter().map(|&x| x != 0).collect()),
            DType::Str => TensorData::Str(Vec::new()),
        }
    }

    /// Values widened to f64 (strings give nothing); for comparisons and statistics.
    pub fn to_f64(&self) -> Vec<f64> {
        match self {
            TensorData::F32(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::F64(v) => v.clone(),
            TensorData::F16(v) => v.iter().map(|x| x.to_f64()).collect(),
            TensorData::Bf16(v) => v.iter().map(|x| x.to_f64()).collect(),
            TensorData::I8(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::I16(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::I32(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::I64(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::U8(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::U16(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::U32(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::U64(v) => v.iter().map(|&x| x as f64).collect(),
            TensorData::Bool(v) => v.iter().map(|&x| x as u8 as f64).collect(),
            TensorData::Str(_) => Vec::new(),
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    pub shape: Vec<usize>,
    pub data: TensorData,
}

impl Tensor {
    pub fn new(shape: Vec<usize>, data: TensorData) -> Tensor {
        debug_assert_eq!(shape.iter().product::<usize>(), data.len());
        Tensor { shape, data }
    }

    pub fn f32(shape: Vec<usize>, v: Vec<f32>) -> Tensor {
        Tensor::new(shape, TensorData::F32(v))
    }

    pub fn dtype(&self) -> DType {
        self.data.dtype()
    }

    pub fn len(&self) -> usize {
        self.data.len()
    }

    pub fn is_empty(&self) -> bool {
        self.data.is_empty()
    }

    pub fn as_f32(&self) -> Option<&[f32]> {
        match &self.data {
            TensorData::F32(v) => Some(v),
            _ => None,
        }
    }

    /// Integer values of an int tensor (i64/i32/u8/...), as ONNX shape inputs carry them.
    pub fn as_i64s(&self) -> Option<Vec<i64>> {
        Some(match &self.data {
            TensorData::I64(v) => v.clone(),
            TensorData::I32(v) => v.iter().map(|&x| x as i64).collect(),
            TensorData::I16(v) => v.iter().map(|&x| x as i64).collect(),
            TensorData::I8(v) => v.iter().map(|&x| x as i64).collect(),
            TensorData::U8(v) => v.iter().map(|&x| x as i64).collect(),
            TensorData::U16(v) => v.iter().map(|&x| x as i64).collect(),
            TensorData::U32(v) => v.iter().map(|&x| x as i64).collect(),
            TensorData::Bool(v) => v.iter().map(|&x| x as i64).collect(),
            _ => return None,
        })
    }

    /// The entries at positions `idx` along `axis` (a gather with constant indices), any
    /// numeric dtype; `None` for strings or an axis out of range.
    pub fn select(&self, axis: usize, idx: &[usize]) -> Option<Tensor> {
        let dim = *self.shape.get(axis)?;
        if idx.iter().any(|&i| i >= dim) {
            return None;
        }
        let outer: usize = self.shape[..axis].iter().product();
        let size = self.dtype().size_of();
        let row = self.shape[axis + 1..].iter().product::<usize>() * size;
        let bytes = self.data.to_le_bytes()?;
        let mut out = Vec::with_capacity(outer * idx.len() * row);
        for o in 0..outer {
            for &i in idx {
                let at = (o * dim + i) * row;
                out.extend_from_slice(&bytes[at..at + row]);
            }
        }
        let mut shape = self.shape.clone();
        shape[axis] = idx.len();
        Some(Tensor::new(shape, TensorData::from_le_bytes(self.dtype(), &out)))
    }

    /// Bitwise equality, NaN payloads included: what "bit-identical outputs" means.
    pub fn bit_identical(&self, other: &Tensor) -> bool {
        if self.shape != other.shape || self.dtype() != other.dtype() {
            return false;
        }
        match (self.data.to_le_bytes(), other.data.to_le_bytes()) {
            (Some(a), Some(b)) => a == b,
            _ => self.data == other.data,
        }
    }
}
