//! Minimal `.npy` (NumPy format 1.0-3.0) reading and writing for float arrays, C order.

use anyhow::{anyhow, bail, Context, Result};
use std::path::Path;

/// Header sizes beyond this are not NumPy files we wrote or should trust.
const MAX_HEADER: usize = 1 << 16;

pub struct NpyArray {
    pub shape: Vec<usize>,
    pub data: Vec<f32>,
}

pub fn read(path: &Path) -> Result<NpyArray> {
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    parse(&bytes).with_context(|| format!("{}", path.display()))
}

pub fn parse(b: &[u8]) -> Result<NpyArray> {
    if b.len() < 10 || &b[..6] != b"\x93NUMPY" {
        bail!("not a .npy file (magic bytes missing)");
    }
    let (hlen, start) = match b[6] {
        1 => (u16::from_le_bytes([b[8], b[9]]) as usize, 10),
        2 | 3 if b.len() >= 12 => (u32::from_le_bytes([b[8], b[9], b[10], b[11]]) as usize, 12),
        v => bail!("unsupported .npy version {v}"),
    };
    if hlen > MAX_HEADER || start + hlen > b.len() {
        bail!(".npy header length {hlen} is out of bounds");
    }
    let header = std::str::from_utf8(&b[start..start + hlen]).map_err(|_| anyhow!(".npy header is not text"))?;
    let field = |k: &str| -> Result<&str> {
        let i = header.find(&format!("'{k}'")).ok_or_else(|| anyhow!(".npy header has no '{k}'"))?;
        Ok(header[i + k.len() + 2..].trim_start().trim_start_matches(':').trim_start())
    };
    let descr = field("descr")?;
    let size = if descr.starts_with("'<f4'") { 4 } else if descr.starts_with("'<f8'") { 8 } else { bail!("unsupported .npy dtype {}: use float32 or float64", &descr[..descr.find(',').unwrap_or(descr.len())]) };
    if field("fortran_order")?.starts_with("True") {
        bail!("Fortran-ordered .npy arrays are not supported; save with np.ascontiguousarray");
    }
    let shape_str = field("shape")?;
    let open = shape_str.strip_prefix('(').ok_or_else(|| anyhow!("bad .npy shape: expected '(' after 'shape'"))?;
    let inner = &open[..open.find(')').ok_or_else(|| anyhow!("bad .npy shape: no ')'"))?];
    let shape: Vec<usize> = inner.split(',').map(str::trim).filter(|s| !s.is_empty()).map(|s| s.parse().map_err(|_| anyhow!("bad .npy dimension '{s}'"))).collect::<Result<_>>()?;
    let n = shape.iter().try_fold(1usize, |a, &d| a.checked_mul(d)).ok_or_else(|| anyhow!(".npy shape overflows"))?;
    let body = &b[start + hlen..];
    let need = n.checked_mul(size).ok_or_else(|| anyhow!(".npy shape {shape:?} overflows"))?;
    if body.len() != need {
        bail!(".npy body holds {} bytes, shape {shape:?} needs {need}", body.len());
    }
    let data = if size == 4 {
        body.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
    } else {
        body.chunks_exact(8).map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")) as f32).collect()
    };
    Ok(NpyArray { shape, data })
}

/// Serializes a float32 array (format 1.0, header padded to 64 bytes as NumPy does).
pub fn to_bytes(shape: &[usize], data: &[f32]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let shape_txt = if dims.len() == 1 { format!("({},)", dims[0]) } else { format!("({})", dims.join(", ")) };
    let mut header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape_txt}, }}");
    let total = 10 + header.len() + 1;
    header.push_str(&" ".repeat((64 - total % 64) % 64));
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend(data.iter().flat_map(|v| v.to_le_bytes()));
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn round_trip() {
        let b = super::to_bytes(&[2, 3], &[1.0, 2.0, 3.0, 4.0, 5.0, 6.5]);
        assert_eq!((b.len() - 24) % 64, 0, "header padded to 64 bytes");
        let a = super::parse(&b).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data[5], 6.5);
        assert!(super::parse(&b[..b.len() - 1]).is_err());
    }
}
