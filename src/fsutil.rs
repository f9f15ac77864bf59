//! Output files appear whole or not at all: write a temp file beside the target, then rename.

use anyhow::{Context, Result};
use std::io::Write;
use std::path::Path;

pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("out");
    let tmp = dir.join(format!(".{name}.{}.tmp", std::process::id()));
    let result = (|| -> std::io::Result<()> {
        let mut f = std::fs::File::create(&tmp)?;
        f.write_all(bytes)?;
        f.sync_all()?;
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result.with_context(|| format!("cannot write {}", path.display()))
}

/// Creates `dir` (and parents) if needed, refusing a path that exists as a file.
pub fn ensure_dir(dir: &Path) -> Result<()> {
    if dir.exists() && !dir.is_dir() {
        anyhow::bail!("output path {} exists and is not a folder; pick another -o", dir.display());
    }
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create output folder {}", dir.display()))
}

/// An output folder built under a temporary sibling name and moved into place whole by
/// [`StagedDir::commit`]: an existing folder is replaced, never merged, and a failure (or a
/// `kill -9`) leaves it as it was. A temporary sibling left by a killed run is removed by the
/// next run into the same place.
pub struct StagedDir {
    target: std::path::PathBuf,
    tmp: std::path::PathBuf,
    committed: bool,
}

const STAGE_TAG: &str = ".pdi-partial-";

impl StagedDir {
    pub fn new(target: &Path) -> Result<StagedDir> {
        if target.exists() && !target.is_dir() {
            anyhow::bail!("output path {} exists and is not a folder; pick another -o", target.display());
        }
        let name = target.file_name().and_then(|n| n.to_str()).filter(|n| *n != "..").ok_or_else(|| anyhow::anyhow!("output path {} has no folder name; pick another -o", target.display()))?;
        let parent = target.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        std::fs::create_dir_all(parent).with_context(|| format!("cannot create {}", parent.display()))?;
        remove_stale(parent, name);
        let tmp = parent.join(format!(".{name}{STAGE_TAG}{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&tmp);
        std::fs::create_dir(&tmp).with_context(|| format!("cannot create output folder beside {}", target.display()))?;
        Ok(StagedDir { target: target.to_path_buf(), tmp, committed: false })
    }

    /// Where the command writes the folder's files until the commit.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// Moves the folder into place: one atomic exchange with an existing folder where the
    /// filesystem has it (Linux), else remove-then-rename.
    pub fn commit(mut self) -> Result<()> {
        if self.target.is_dir() {
            if !exchange(&self.tmp, &self.target) {
                std::fs::remove_dir_all(&self.target).with_context(|| format!("cannot replace {}", self.target.display()))?;
                std::fs::rename(&self.tmp, &self.target).with_context(|| format!("cannot move the output into {}", self.target.display()))?;
            }
        } else {
            std::fs::rename(&self.tmp, &self.target).with_context(|| format!("cannot move the output into {}", self.target.display()))?;
        }
        self.committed = true;
        // After an exchange the old folder sits at the temporary name.
        let _ = std::fs::remove_dir_all(&self.tmp);
        Ok(())
    }
}

impl Drop for StagedDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// Removes temporary siblings of `name` whose process is gone.
fn remove_stale(parent: &Path, name: &str) {
    let prefix = format!(".{name}{STAGE_TAG}");
    for e in std::fs::read_dir(parent).into_iter().flatten().flatten() {
        let file = e.file_name();
        let Some(pid) = file.to_str().and_then(|f| f.strip_prefix(&prefix)).and_then(|p| p.parse::<u32>().ok()) else { continue };
        let alive = pid == std::process::id() || (cfg!(target_os = "linux") && Path::new(&format!("/proc/{pid}")).exists());
        if !alive {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// Swaps two paths in one step (renameat2 with RENAME_EXCHANGE); false where unsupported.
#[cfg(target_os = "linux")]
fn exchange(a: &Path, b: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let (Ok(a), Ok(b)) = (std::ffi::CString::new(a.as_os_str().as_bytes()), std::ffi::CString::new(b.as_os_str().as_bytes())) else { return false };
    // SAFETY: both are valid NUL-terminated paths; the call only reads them.
    unsafe { libc::renameat2(libc::AT_FDCWD, a.as_ptr(), libc::AT_FDCWD, b.as_ptr(), libc::RENAME_EXCHANGE) == 0 }
}

#[cfg(not(target_os = "linux"))]
fn exchange(_: &Path, _: &Path) -> bool {
    false
}

#[cfg(test)]
mod tests {
    use super::StagedDir;

    #[test]
    fn a_staged_folder_replaces_the_old_one_whole_or_not_at_all() {
        let root = tempfile::tempdir().unwrap();
        let out = root.path().join("out");
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join("stale.txt"), "old").unwrap();
        // A failed run: dropped uncommitted, the old folder is as it was and nothing is left beside it.
        let s = StagedDir::new(&out).unwrap();
        std::fs::write(s.path().join("model.onnx"), "new").unwrap();
        drop(s);
        assert!(out.join("stale.txt").exists() && !out.join("model.onnx").exists());
        assert_eq!(std::fs::read_dir(root.path()).unwrap().count(), 1);
        // A killed run's sibling (a pid that cannot be alive) goes at the next run.
        std::fs::create_dir(root.path().join(".out.pdi-partial-4294967295")).unwrap();
        let s = StagedDir::new(&out).unwrap();
        std::fs::write(s.path().join("model.onnx"), "new").unwrap();
        s.commit().unwrap();
        assert!(!out.join("stale.txt").exists(), "replaced, not merged");
        assert_eq!(std::fs::read_to_string(out.join("model.onnx")).unwrap(), "new");
        assert_eq!(std::fs::read_dir(root.path()).unwrap().count(), 1, "no sibling left");
    }
}
