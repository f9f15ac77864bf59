//! Every command in docs/guide/ runs: each page's `sh` blocks, copied as they are, run by
//! bash in a scratch folder that holds the repository's models and calibration and an `out/`,
//! with `pdi-compile` on the PATH. Training is shortened: the scratch `passes/` are the
//! shipped recipes with `steps:` cut to 8 and training `frames:` to 32, so the pages cannot
//! drift from the tool without a test failing, and the suite does not train for hours.

use crate::common::repo;
use std::path::Path;

/// The `sh` blocks of a guide page, in order.
fn blocks(page: &str) -> Vec<String> {
    let text = std::fs::read_to_string(repo().join("docs/guide").join(page)).unwrap();
    let (mut out, mut current): (Vec<String>, Option<String>) = (Vec::new(), None);
    for line in text.lines() {
        match (&mut current, line.trim_end()) {
            (None, "```sh") => current = Some(String::new()),
            (Some(b), "```") => {
                out.push(std::mem::take(b));
                current = None;
            }
            (Some(b), l) => {
                b.push_str(l);
                b.push('\n');
            }
            _ => {}
        }
    }
    out
}

/// A scratch folder laid out like the repository root, with short-training recipes.
fn scratch() -> tempfile::TempDir {
    let dir = tempfile::tempdir().unwrap();
    for d in ["models", "calib"] {
        std::os::unix::fs::symlink(repo().join(d), dir.path().join(d)).unwrap();
    }
    std::fs::create_dir(dir.path().join("passes")).unwrap();
    for e in std::fs::read_dir(repo().join("passes")).unwrap() {
        let p = e.unwrap().path();
        let text = std::fs::read_to_string(&p).unwrap();
        let short = shorten(&text);
        std::fs::write(dir.path().join("passes").join(p.file_name().unwrap()), short).unwrap();
    }
    dir
}

/// `steps: N` → 8 and `frames: N` → 32 on the lines of the passes that train.
fn shorten(text: &str) -> String {
    let mut out = String::new();
    for line in text.lines() {
        let trains = ["recover:", "qat:", "rknn-qat:"].iter().any(|k| line.contains(k));
        let mut l = line.to_string();
        if trains {
            for (key, to) in [("steps: ", "8"), ("frames: ", "32")] {
                let mut rest = l.as_str();
                let mut done = String::new();
                while let Some(at) = rest.find(key) {
                    let (head, tail) = rest.split_at(at + key.len());
                    // The key itself, not the end of another (`calib_frames: `).
                    let whole = at == 0 || matches!(rest.as_bytes()[at - 1], b' ' | b'{');
                    let digits = if whole { tail.chars().take_while(|c| c.is_ascii_digit()).count() } else { 0 };
                    done.push_str(head);
                    if digits > 0 {
                        done.push_str(to);
                    }
                    rest = &tail[digits..];
                }
                done.push_str(rest);
                l = done;
            }
        }
        out.push_str(&l);
        out.push('\n');
    }
    out
}

/// Runs `pages` in order in one scratch folder; each block must exit 0.
fn run_pages(pages: &[&str]) {
    let dir = scratch();
    let bin = Path::new(env!("CARGO_BIN_EXE_pdi-compile")).parent().unwrap().to_path_buf();
    let path = format!("{}:{}", bin.display(), std::env::var("PATH").unwrap_or_default());
    for page in pages {
        let bs = blocks(page);
        assert!(!bs.is_empty(), "{page} has no sh block");
        for b in bs {
            let t = std::time::Instant::now();
            let out = std::process::Command::new("bash").args(["-euo", "pipefail", "-c", &b]).current_dir(dir.path()).env("PATH", &path).output().unwrap();
            let tail = |v: &[u8]| String::from_utf8_lossy(v).lines().rev().take(15).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n");
            assert!(out.status.success(), "docs/guide/{page}: block\n{b}exited {:?}\nstdout:\n{}\nstderr:\n{}", out.status.code(), tail(&out.stdout), tail(&out.stderr));
            println!("docs/guide/{page}: {:.1} s for\n{b}", t.elapsed().as_secs_f64());
        }
    }
}

#[test]
fn shortening_touches_only_training() {
    let r = shorten("  - recover: {steps: 8000, lr: 2.0e-3, batch: 8, frames: 2048}\n  - quantize: {calib_frames: 64, qat: {teacher: original, steps: 3500, lr: 1.0e-3, frames: 4096}}\n  - quantize: {calib_frames: 64}\n");
    assert_eq!(r, "  - recover: {steps: 8, lr: 2.0e-3, batch: 8, frames: 32}\n  - quantize: {calib_frames: 64, qat: {teacher: original, steps: 8, lr: 1.0e-3, frames: 32}}\n  - quantize: {calib_frames: 64}\n");
}

#[test]
fn every_guide_page_is_run() {
    let mut pages: Vec<String> = std::fs::read_dir(repo().join("docs/guide")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    pages.sort();
    assert_eq!(pages, ["README.md", "compile.md", "gate.md", "prune.md", "quantize.md", "rknn.md", "run.md", "scene.md", "stress.md"], "a new page needs a test below");
}

#[test]
fn guide_quantize() {
    run_pages(&["README.md", "quantize.md"]);
}

#[test]
fn guide_rknn() {
    run_pages(&["README.md", "rknn.md"]);
}

#[test]
fn guide_scene() {
    run_pages(&["README.md", "scene.md"]);
}

#[test]
fn guide_gate() {
    run_pages(&["README.md", "gate.md"]);
}

/// compile, then prune, run (which draws the pruned model against the lossless one) and stress
/// (which takes the lossless compile as a candidate): each reads its predecessors' folders.
#[test]
fn guide_prune_run_stress() {
    run_pages(&["README.md", "compile.md", "prune.md", "run.md", "stress.md"]);
}
