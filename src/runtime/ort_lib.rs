//! Finding and loading the ONNX Runtime shared library (`load-dynamic`).
//!
//! The reference runtime is the one the PyPI wheel `onnxruntime==1.31.1` ships, so that the
//! numbers we compare against are the ones users get from Python.

use anyhow::{anyhow, bail, Context, Result};
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

pub const ORT_VERSION: &str = "1.31.1";
const FIX: &str = "run `scripts/setup` (installs onnxruntime==1.31.1 into the cache) or set PDI_ORT_LIB to libonnxruntime.so";

/// `PDI_ORT_LIB` if set, else the library inside the `onnxruntime` package of `PDI_PYTHON`, of
/// the cache's Python (where `scripts/setup`, and so the demo and the tests, install it), or of
/// `python3`.
pub fn locate() -> Result<PathBuf> {
    let cached = crate::pyenv::cache().ok().map(|c| c.join("pyenv/bin/python")).filter(|p| p.is_file());
    let python = match (std::env::var("PDI_PYTHON"), cached) {
        (Ok(p), _) => p,
        (Err(_), Some(p)) => p.to_string_lossy().into_owned(),
        (Err(_), None) => "python3".into(),
    };
    locate_with(std::env::var_os("PDI_ORT_LIB"), &python)
}

fn locate_with(ort_lib: Option<std::ffi::OsString>, python: &str) -> Result<PathBuf> {
    if let Some(p) = ort_lib {
        let p = PathBuf::from(p);
        if !p.is_file() {
            bail!("PDI_ORT_LIB points to {} which is not a file; {FIX}", p.display());
        }
        return Ok(p);
    }
    let out = std::process::Command::new(python)
        .args(["-c", "import onnxruntime, os; print(os.path.join(os.path.dirname(onnxruntime.__file__), 'capi'))"])
        .output();
    let capi = match out {
        Ok(o) if o.status.success() => PathBuf::from(String::from_utf8_lossy(&o.stdout).trim()),
        _ => bail!("ONNX Runtime library not found (PDI_ORT_LIB unset, `{python}` has no onnxruntime); {FIX}"),
    };
    find_in(&capi).ok_or_else(|| anyhow!("no libonnxruntime.so.* in {}; {FIX}", capi.display()))
}

fn find_in(dir: &Path) -> Option<PathBuf> {
    let mut libs: Vec<PathBuf> = std::fs::read_dir(dir)
        .ok()?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.file_name().and_then(|n| n.to_str()).is_some_and(|n| n.starts_with("libonnxruntime.so")))
        .collect();
    libs.sort(); // the fully versioned name sorts last
    libs.pop()
}

static ENV: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

/// The process-wide ORT environment, loading the library on first use.
pub fn environment() -> Result<&'static ort::environment::Environment> {
    let env = ENV.get_or_init(|| {
        let path = locate().map_err(|e| e.to_string())?;
        let builder = ort::init_from(&path).map_err(|e| format!("cannot load ONNX Runtime from {}: {e}; {FIX}", path.display()))?;
        builder.with_name("pdi-compile").build().map_err(|e| format!("cannot start ONNX Runtime: {e}"))
    });
    env.as_ref().map_err(|e| anyhow!("{e}")).context("ONNX Runtime unavailable")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn missing_library_errors_say_how_to_fix_it() {
        let e = locate_with(Some("/nonexistent/libonnxruntime.so".into()), "python3").unwrap_err().to_string();
        assert!(e.contains("PDI_ORT_LIB") && e.contains("scripts/setup"), "{e}");
        assert!(!e.contains('\n'));
        let e = locate_with(None, "/nonexistent/python").unwrap_err().to_string();
        assert!(e.contains("not found") && e.contains("scripts/setup"), "{e}");
    }
}
