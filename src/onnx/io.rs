//! Loading and saving ONNX files.
//!
//! External data is read only from files inside the model's folder: an absolute `location`
//! or one that climbs out with `..` (or through a symlink) is refused, and offsets and
//! lengths are checked against the file's real size before anything is allocated.
//! Saving writes one self-contained file unless external data is asked for.

use super::proto::{ModelProto, StringStringEntryProto, TensorProto, DATA_LOCATION_EXTERNAL};
use crate::fsutil::write_atomic;
use anyhow::{anyhow, bail, Context, Result};
use prost::Message;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Component, Path, PathBuf};

/// Protobuf's hard limit: a single message cannot exceed 2 GiB.
const PROTOBUF_LIMIT: u64 = 2 << 30;

pub struct Loaded {
    pub model: ModelProto,
    /// Things the user should know that did not stop the load.
    pub warnings: Vec<String>,
}

pub fn load(path: &Path) -> Result<Loaded> {
    let meta = std::fs::metadata(path).with_context(|| format!("cannot read {}", path.display()))?;
    if meta.is_dir() {
        bail!("{} is a folder; give the .onnx file inside it", path.display());
    }
    if meta.len() > PROTOBUF_LIMIT {
        bail!("{} is {} bytes, over protobuf's 2 GiB limit; large weights must be stored as external data", path.display(), meta.len());
    }
    let bytes = std::fs::read(path).with_context(|| format!("cannot read {}", path.display()))?;
    let base = path.parent().map(|p| if p.as_os_str().is_empty() { Path::new(".") } else { p });
    load_bytes(&bytes, base).with_context(|| format!("{}", path.display()))
}

/// Decodes a model; `base` is the folder external data may be read from (none: external data is an error).
pub fn load_bytes(bytes: &[u8], base: Option<&Path>) -> Result<Loaded> {
    let mut model = ModelProto::decode(bytes).map_err(|e| anyhow!("not a valid ONNX protobuf (truncated or corrupt file?): {e}"))?;
    let mut warnings = Vec::new();
    let reencoded = model.encoded_len();
    if reencoded < bytes.len() {
        warnings.push(format!(
            "re-encoding is {} bytes shorter than the file: fields this tool does not know (newer ONNX schema?) were dropped",
            bytes.len() - reencoded
        ));
    }
    if model.graph.is_none() {
        bail!("the file decodes but holds no graph: is it an ONNX model?");
    }
    let mut resolver = ExternalData { base, cache: None };
    for t in all_tensors_mut(&mut model) {
        if t.data_location == DATA_LOCATION_EXTERNAL {
            resolver.inline(t)?;
        }
    }
    Ok(Loaded { model, warnings })
}

/// Every initializer-like tensor: graph initializers, Constant values, sparse parts, subgraphs.
fn all_tensors_mut(model: &mut ModelProto) -> Vec<&mut TensorProto> {
    fn graph<'a>(g: &'a mut super::proto::GraphProto, out: &mut Vec<&'a mut TensorProto>) {
        out.extend(g.initializer.iter_mut());
        for s in &mut g.sparse_initializer {
            out.extend(s.values.as_mut());
            out.extend(s.indices.as_mut());
        }
        for n in &mut g.node {
            for a in &mut n.attribute {
                out.extend(a.t.as_mut());
                out.extend(a.tensors.iter_mut());
                if let Some(sg) = a.g.as_mut() {
                    graph(sg, out);
                }
                for sg in &mut a.graphs {
                    graph(sg, out);
                }
            }
        }
    }
    let mut out = Vec::new();
    if let Some(g) = model.graph.as_mut() {
        graph(g, &mut out);
    }
    out
}

struct ExternalData<'a> {
    base: Option<&'a Path>,
    cache: Option<(PathBuf, std::fs::File, u64)>,
}

impl ExternalData<'_> {
    fn inline(&mut self, t: &mut TensorProto) -> Result<()> {
        let entry = |k: &str| t.external_data.iter().find(|e| e.key == k).map(|e| e.value.clone());
        let location = entry("location").ok_or_else(|| anyhow!("tensor '{}' is external but names no location", t.name))?;
        let parse = |k: &str| -> Result<Option<u64>> {
            entry(k).map(|v| v.parse::<u64>().map_err(|_| anyhow!("tensor '{}': external {k} '{v}' is not a number", t.name))).transpose()
        };
        let (offset, length) = (parse("offset")?.unwrap_or(0), parse("length")?);
        let base = self.base.ok_or_else(|| anyhow!("tensor '{}' uses external data but the model was not loaded from a folder", t.name))?;
        let path = safe_join(base, &location).with_context(|| format!("tensor '{}'", t.name))?;
        if self.cache.as_ref().map(|c| &c.0) != Some(&path) {
            let f = std::fs::File::open(&path).with_context(|| format!("tensor '{}': cannot open external data {}", t.name, path.display()))?;
            let len = f.metadata()?.len();
            self.cache = Some((path.clone(), f, len));
        }
        let (_, file, file_len) = self.cache.as_mut().expect("cache set above");
        let length = length.unwrap_or(file_len.saturating_sub(offset));
        if offset.checked_add(length).is_none_or(|end| end > *file_len) {
            bail!("tensor '{}': external data range {offset}+{length} lies beyond the end of {} ({file_len} bytes)", t.name, location);
        }
        let mut buf = vec![0u8; length as usize];
        file.seek(SeekFrom::Start(offset))?;
        file.read_exact(&mut buf)?;
        t.raw_data = buf;
        t.external_data.clear();
        t.data_location = 0;
        Ok(())
    }
}

/// `base/location`, refusing anything that would leave `base`.
fn safe_join(base: &Path, location: &str) -> Result<PathBuf> {
    let rel = Path::new(location);
    if rel.is_absolute() || location.starts_with('/') || location.starts_with('\\') {
        bail!("external data path '{location}' is absolute; only paths inside the model's folder are allowed");
    }
    if rel.components().any(|c| !matches!(c, Component::Normal(_) | Component::CurDir)) {
        bail!("external data path '{location}' leaves the model's folder; only paths inside it are allowed");
    }
    let joined = base.join(rel);
    let (root, real) = (base.canonicalize()?, joined.canonicalize().with_context(|| format!("external data file '{location}' not found"))?);
    if !real.starts_with(&root) {
        bail!("external data path '{location}' resolves (through a link) outside the model's folder");
    }
    Ok(real)
}

/// Writes `model` as one self-contained file, atomically.
pub fn save(model: &ModelProto, path: &Path) -> Result<()> {
    let len = model.encoded_len() as u64;
    if len > PROTOBUF_LIMIT {
        bail!("model is {len} bytes, over protobuf's 2 GiB limit; compile with --external-data");
    }
    write_atomic(path, &model.encode_to_vec())
}

/// Writes tensors of at least `threshold` bytes to `<file>.data` beside the model.
pub fn save_with_external_data(model: &ModelProto, path: &Path, threshold: usize) -> Result<()> {
    let mut model = model.clone();
    let name = path.file_name().and_then(|n| n.to_str()).ok_or_else(|| anyhow!("bad output path {}", path.display()))?;
    let data_name = format!("{name}.data");
    let mut blob = Vec::new();
    for t in all_tensors_mut(&mut model) {
        if t.raw_data.len() >= threshold {
            // 4 KiB alignment lets readers mmap each tensor.
            blob.resize(blob.len().div_ceil(4096) * 4096, 0);
            let kv = |k: &str, v: String| StringStringEntryProto { key: k.into(), value: v };
            t.external_data = vec![
                kv("location", data_name.clone()),
                kv("offset", blob.len().to_string()),
                kv("length", t.raw_data.len().to_string()),
            ];
            blob.extend_from_slice(&std::mem::take(&mut t.raw_data));
            t.data_location = DATA_LOCATION_EXTERNAL;
        }
    }
    write_atomic(&path.with_file_name(&data_name), &blob)?;
    save(&model, path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::onnx::proto::GraphProto;

    fn model_with(t: TensorProto) -> ModelProto {
        ModelProto { ir_version: 8, graph: Some(GraphProto { initializer: vec![t], ..Default::default() }), ..Default::default() }
    }

    #[test]
    fn external_data_round_trip_and_escapes() {
        let dir = tempfile::tempdir().unwrap();
        let t = TensorProto { name: "w".into(), dims: vec![2000], data_type: 1, raw_data: vec![7u8; 8000], ..Default::default() };
        let p = dir.path().join("m.onnx");
        save_with_external_data(&model_with(t.clone()), &p, 1024).unwrap();
        assert!(std::fs::metadata(&p).unwrap().len() < 1000);
        let back = load(&p).unwrap().model;
        assert_eq!(back.graph.unwrap().initializer[0], t);

        for (loc, needle) in [("/etc/passwd", "absolute"), ("../x.data", "leaves"), ("a/../../x", "leaves")] {
            let mut e = t.clone();
            e.raw_data.clear();
            e.data_location = DATA_LOCATION_EXTERNAL;
            e.external_data = vec![StringStringEntryProto { key: "location".into(), value: loc.into() }];
            let bytes = model_with(e).encode_to_vec();
            let err = format!("{:#}", load_bytes(&bytes, Some(dir.path())).err().unwrap());
            assert!(err.contains(needle), "{loc}: {err}");
        }
    }
}
