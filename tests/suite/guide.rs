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

/// `PATH` with the built `pdi-compile` first, as a reader's shell would find it.
fn path_with_the_binary() -> String {
    let bin = Path::new(env!("CARGO_BIN_EXE_pdi-compile")).parent().unwrap().to_path_buf();
    format!("{}:{}", bin.display(), std::env::var("PATH").unwrap_or_default())
}

/// Runs `pages` in order in one scratch folder; each block must exit 0.
fn run_pages(pages: &[&str]) {
    let dir = scratch();
    let path = path_with_the_binary();
    for page in pages {
        let bs = blocks(page);
        assert!(!bs.is_empty(), "{page} has no sh block");
        for b in bs {
            let t = std::time::Instant::now();
            let out = std::process::Command::new("bash").args(["-euo", "pipefail", "-c", &b]).current_dir(dir.path()).env("PATH", &path).output().unwrap();
            let tail = |v: &[u8]| String::from_utf8_lossy(v).lines().rev().take(15).collect::<Vec<_>>().into_iter().rev().collect::<Vec<_>>().join("\n");
            assert!(out.status.success(), "docs/guide/{page}: block\n{b}exited {:?}\nstdout:\n{}\nstderr:\n{}", out.status.code(), tail(&out.stdout), tail(&out.stderr));
            for (command, written, expected) in promised(&b) {
                assert!(dir.path().join(&written).exists(), "docs/guide/{page}: `pdi-compile {command} ... -o {written}` wrote nothing");
                for f in expected {
                    assert!(dir.path().join(&written).join(f).exists(), "docs/guide/{page}: `pdi-compile {command} ... -o {written}` wrote no {f}");
                }
            }
            println!("docs/guide/{page}: {:.1} s for\n{b}", t.elapsed().as_secs_f64());
        }
    }
}

/// What each `pdi-compile COMMAND ... -o OUT` line of a block promises: (command, OUT, the
/// files the command always writes there).
fn promised(block: &str) -> Vec<(String, String, &'static [&'static str])> {
    let mut out = Vec::new();
    for line in block.lines() {
        let words: Vec<&str> = line.split_whitespace().collect();
        let (Some(0), Some(o)) = (words.iter().position(|w| *w == "pdi-compile"), words.iter().position(|w| *w == "-o")) else { continue };
        let (Some(command), Some(written)) = (words.get(1), words.get(o + 1)) else { continue };
        let expected: &'static [&'static str] = match *command {
            "compile" | "rebuild" => &["model.onnx", "report.json", "manifest.yaml"],
            "run" => &["run.json", "detections.json"],
            _ => &[],
        };
        out.push((command.to_string(), written.to_string(), expected));
    }
    out
}

#[test]
fn a_block_promises_the_folders_it_names() {
    let p = promised("pdi-compile psf simulate --lens x.yaml -o out/psf\npdi-compile run out/f32 --frames f -o out/run\necho -o x\n");
    assert_eq!(p.iter().map(|(c, w, e)| (c.as_str(), w.as_str(), e.len())).collect::<Vec<_>>(), [("psf", "out/psf", 0), ("run", "out/run", 2)]);
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

/// The messages the pages quote under "What can go wrong" (`error: ...`, `warning: ...` in
/// backticks, folded over lines), with their page.
fn quoted() -> Vec<(String, String)> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(repo().join("docs/guide")).unwrap() {
        let path = e.unwrap().path();
        let text = std::fs::read_to_string(&path).unwrap();
        for start in ["- `error: ", "- `warning: "] {
            for (at, _) in text.match_indices(start) {
                let body = &text[at + 3..];
                let end = body.find('`').expect("a closed quote");
                out.push((path.file_name().unwrap().to_string_lossy().into_owned(), body[..end].split_whitespace().collect::<Vec<_>>().join(" ")));
            }
        }
    }
    out.sort();
    out
}

/// Whitespace collapsed and every number written `N`: a quote shows one run's figures.
fn normalized(s: &str) -> String {
    let s = s.split_whitespace().collect::<Vec<_>>().join(" ");
    let mut out = String::new();
    let mut chars = s.chars().peekable();
    while let Some(c) = chars.next() {
        if c.is_ascii_digit() {
            while chars.peek().is_some_and(|d| d.is_ascii_digit() || *d == '.' || *d == 'e') {
                chars.next();
            }
            out.push('N');
        } else {
            out.push(c);
        }
    }
    out
}

/// Whether `stderr` says `quote`: its pieces between `...` (and placeholders such as `DIR`)
/// in order, numbers aside.
fn says(stderr: &str, quote: &str) -> bool {
    let placeholder = |w: &str| {
        let core = w.trim_end_matches(|c: char| c.is_ascii_punctuation());
        if core.len() >= 3 && core.chars().all(|c| c.is_ascii_uppercase()) { format!("...{}", &w[core.len()..]) } else { w.to_string() }
    };
    let quote: String = quote.split(' ').map(placeholder).collect::<Vec<_>>().join(" ");
    let (stderr, quote) = (normalized(stderr), normalized(&quote));
    let mut rest = stderr.as_str();
    for piece in quote.split("...").map(str::trim).filter(|p| !p.is_empty()) {
        let Some(at) = rest.find(piece) else { return false };
        rest = &rest[at + piece.len()..];
    }
    true
}

#[test]
fn a_quote_matches_what_it_quotes_and_nothing_else() {
    assert!(says("error: --calib /x/empty: no frames (PNG/TIFF)", "error: --calib DIR: no frames"));
    assert!(says("warning: rel L2 0.117 from float on 8 frames", "warning: rel L2 0.263 from float on 16 frames"));
    assert!(!says("error: pipeline r.yaml: line 3: unknown option", "error: ... opset ... above 19"));
    assert!(!says("error: b then a", "error: a ... b"));
}

/// Every message a page quotes is what the tool prints when the page's mistake is made: each
/// quote has a command below that makes it (a new quote without one fails), with the exit code
/// the page gives.
#[test]
fn the_messages_the_guide_quotes_are_what_the_tool_prints() {
    let dir = scratch();
    let path = path_with_the_binary();
    let python = std::env::var("PDI_PYTHON").expect("PDI_PYTHON is not set: run the suite with scripts/test, which installs onnx and pillow");
    let tiny = "models/trained/pdinet_v5_tiny_trained.onnx";
    let psf = "--psf calib/single_lwir_blur.npy";
    let int8 = |from: &str, to: &str| format!("sed 's/{from}/{to}/' passes/detect-int8.yaml > q.yaml && pdi-compile compile {tiny} --pipeline q.yaml {psf}");
    // (a piece of the quote, the mistake, the exit code)
    let cases: Vec<(&str, String, i32)> = vec![
        ("bind-psf: the blur map", "pdi-compile compile models/fixtures/pdinet_v5_input_op17_nofold.onnx --pipeline passes/detect-f32.yaml -o out/a".into(), 2),
        ("unknown pass 'fold-bnn'", format!("printf 'name: r\\npasses: [strip-recon, fold-bnn]\\n' > my.yaml && pdi-compile compile {tiny} --pipeline my.yaml -o out/b"), 2),
        ("no reconstruction output", format!("pdi-compile compile models/fixtures/exports/pdinet_v5_input_op17_nofold_detonly.onnx --pipeline passes/detect-f32.yaml {psf} -o out/c"), 0),
        ("needs teacher from an earlier pass", format!("printf 'name: my\\nbase: detect-lossless\\npasses:\\n  - recover: {{steps: 8}}\\n' > my.yaml && pdi-compile compile {tiny} --pipeline my.yaml {psf} -o out/d"), 2),
        ("missed its error budget", int8("error_budget: 0.1", "error_budget: 1.0e-6, max_float_layers: 0") + " -o out/e", 0),
        ("past the hard limit", int8("error_budget: 0.1", "error_budget: 0.1, hard_limit: {max_rel_l2: 1.0e-6}") + " -o out/f", 1),
        ("holds no .png", format!("mkdir -p empty && pdi-compile compile {tiny} --pipeline passes/detect-int8.yaml {psf} --calib empty -o out/g"), 2),
        ("opset", format!("'{python}' -c \"import onnx; m = onnx.load('models/fixtures/pdinet_v8_const_op13_fold.onnx'); [setattr(o, 'version', 21) for o in m.opset_import if o.domain in ('', 'ai.onnx')]; onnx.save(m, 'op21.onnx')\" && pdi-compile compile op21.onnx --pipeline passes/detect-rknn.yaml -o out/h"), 2),
        ("32-bit samples", format!("pdi-compile run {tiny} {psf} --frames out/frames -o out/i"), 2),
        ("takes the camera's blur map", format!("mkdir -p one && '{python}' -c \"import numpy, PIL.Image; PIL.Image.fromarray(numpy.zeros((192, 256), numpy.uint16)).save('one/a.png')\" && pdi-compile run {tiny} --frames one -o out/j"), 2),
        ("multiples of 32", format!("printf 'roi: {{x: 10, y: 0, w: 64, h: 64}}\\n' > s.yaml && pdi-compile compile {tiny} --pipeline passes/detect-f32.yaml {psf} --scene s.yaml -o out/k"), 2),
        ("class 'Boat'", format!("printf 'classes: [Boat]\\n' > s.yaml && pdi-compile compile {tiny} --pipeline passes/detect-f32.yaml {psf} --scene s.yaml -o out/l"), 2),
        ("no stress condition 'gain_x3'", int8("error_budget: 0.1", "error_budget: 0.1, calib_conditions: [gain_x3]") + " -o out/m", 2),
    ];
    // A float RGB TIFF (32-bit samples), which the image decoder reads and `run` refuses.
    std::fs::create_dir_all(dir.path().join("out/frames")).unwrap();
    image::DynamicImage::ImageRgb32F(image::Rgb32FImage::from_pixel(8, 8, image::Rgb([0.5, 0.5, 0.5]))).save(dir.path().join("out/frames/x.tif")).unwrap();
    let quotes = quoted();
    let mut wrong = Vec::new();
    for (page, quote) in &quotes {
        let Some((_, command, code)) = cases.iter().find(|(piece, _, _)| quote.contains(piece)) else { panic!("docs/guide/{page} quotes `{quote}`: add the mistake that makes it to this test") };
        let out = std::process::Command::new("bash").args(["-euo", "pipefail", "-c", &format!("{command} > /dev/null || exit $?")]).current_dir(dir.path()).env("PATH", &path).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        if out.status.code() != Some(*code) {
            wrong.push(format!("docs/guide/{page}: `{command}` exited {:?}, not {code}: {}", out.status.code(), stderr.trim()));
        } else if !says(&stderr, quote) {
            wrong.push(format!("docs/guide/{page} quotes\n  {quote}\nwhere the tool says\n  {}", stderr.trim()));
        }
    }
    assert!(wrong.is_empty(), "{}", wrong.join("\n"));
    assert_eq!(quotes.len(), cases.len(), "a case here that no page quotes any more");
}
