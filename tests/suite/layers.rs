//! Dependencies point down: each top-level module of `src/` has a layer, and a module imports
//! only from its own layer or below; no two modules import each other, directly or through
//! others (a circle within a layer is a circle too), and no two files either; `passes` is
//! imported only by the pipeline and the commands, `prune` only by `passes`. The tests fail
//! on an import that breaks any of these, and on a module that has no layer.

use crate::common::repo;
use std::collections::{BTreeMap, BTreeSet};

/// Lowest first. Modules in one layer may import each other.
const LAYERS: &[&[&str]] = &[
    &["tensor", "fsutil", "warn", "canvas", "clock"],
    &["onnx", "ir"],
    &["analysis", "metrics", "detect", "optics", "inspect", "ridge"],
    &["runtime", "frames", "dataset", "calib_frames", "pyenv", "torch"],
    // analyses and rewrites: quantization compares a crop with its model through the scene's
    // view; the targets read the scene's metadata and emulate the toolkit's points as QDQ
    &["prune", "scene"],
    &["quant"],
    &["targets"],
    &["passes"],
    &["pipeline"],
    // libraries the commands share: running an artifact, comparing two models, the manifest
    &["deploy", "verify", "manifest"],
    // commands, and what bench and ship share (variants compiled and timed side by side)
    &["compile", "rebuild", "run", "ship", "bench", "variants", "stress", "cli", "fuzz_targets", "reference"],
];

/// Top-level module → the top-level modules its files name through `crate::`.
fn imports() -> BTreeMap<String, BTreeSet<String>> {
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut stack = vec![repo().join("src")];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            if p.extension().is_none_or(|x| x != "rs") {
                continue;
            }
            let rel = p.strip_prefix(repo().join("src")).unwrap();
            let top = rel.components().next().unwrap().as_os_str().to_string_lossy().trim_end_matches(".rs").to_string();
            if top == "lib" || top == "main" {
                continue;
            }
            let text = std::fs::read_to_string(&p).unwrap();
            let entry = edges.entry(top.clone()).or_default();
            for (i, _) in text.match_indices("crate::") {
                let name: String = text[i + 7..].chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
                if !name.is_empty() && name != top {
                    entry.insert(name);
                }
            }
        }
    }
    edges
}

#[test]
fn dependencies_point_down() {
    let layer = |m: &str| LAYERS.iter().position(|l| l.contains(&m));
    let edges = imports();
    let mut problems = Vec::new();
    for (from, tos) in &edges {
        let Some(lf) = layer(from) else {
            problems.push(format!("src/{from} has no layer: add it to LAYERS"));
            continue;
        };
        for to in tos {
            let Some(lt) = layer(to) else { continue };
            if lt > lf {
                problems.push(format!("{from} (layer {lf}) imports {to} (layer {lt}): an import that points up"));
            }
            if to == "passes" && lf < layer("pipeline").unwrap() {
                problems.push(format!("{from} imports passes: only the pipeline and the commands may"));
            }
            if to == "prune" && from != "passes" {
                problems.push(format!("{from} imports prune: only passes may (training lives in torch, least squares in ridge)"));
            }
        }
    }
    for circle in circles(&edges) {
        problems.push(format!("an import circle: {}", circle.join(" -> ")));
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    // The modules the map names exist: a stale name would hide a module that lost its layer.
    for m in LAYERS.iter().flat_map(|l| l.iter()) {
        assert!(edges.contains_key(*m), "LAYERS names src/{m}, which does not exist");
    }
}

/// Every module that reaches itself through imports, as the path back to it (one per module).
fn circles(edges: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    let mut found = Vec::new();
    for start in edges.keys() {
        // Breadth first from `start`, remembering each module's predecessor.
        let mut before: BTreeMap<&str, &str> = BTreeMap::new();
        let mut queue = std::collections::VecDeque::from([start.as_str()]);
        while let Some(m) = queue.pop_front() {
            for next in edges.get(m).into_iter().flatten() {
                if next == start {
                    let mut path = vec![start.clone(), m.to_string()];
                    let mut at = m;
                    while let Some(p) = before.get(at) {
                        path.insert(1, p.to_string());
                        at = p;
                    }
                    path.dedup();
                    path.push(start.clone());
                    found.push(path);
                    queue.clear();
                    break;
                }
                if !before.contains_key(next.as_str()) && next != start {
                    before.insert(next, m);
                    queue.push_back(next);
                }
            }
        }
    }
    found
}

/// File-level imports: each file of `src/` by its module path (`targets::rknn`; a folder's
/// `mod.rs` by the folder's), to the files it names through `crate::` or `super::`. A module
/// naming its own descendants declares or re-exports them: not an import.
fn file_imports() -> BTreeMap<String, BTreeSet<String>> {
    let src = repo().join("src");
    let mut files = BTreeMap::new();
    let mut stack = vec![src.clone()];
    while let Some(dir) = stack.pop() {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                let rel = p.strip_prefix(&src).unwrap().with_extension("");
                let mut parts: Vec<String> = rel.components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
                if parts.last().is_some_and(|l| l == "mod") {
                    parts.pop();
                }
                if parts != ["lib"] && parts != ["main"] {
                    files.insert(parts.join("::"), std::fs::read_to_string(&p).unwrap());
                }
            }
        }
    }
    let is_mod_rs = |m: &str| repo().join("src").join(m.replace("::", "/")).join("mod.rs").exists();
    // The longest module path that `path` starts with.
    let resolve = |path: &[String]| (1..=path.len()).rev().map(|n| path[..n].join("::")).find(|m| files.contains_key(m));
    let ident = |t: &str| -> String { t.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect() };
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (module, text) in &files {
        let own: Vec<String> = module.split("::").map(str::to_string).collect();
        let parent: Vec<String> = if is_mod_rs(module) { own[..own.len() - 1].to_vec() } else { own[..own.len().saturating_sub(1)].to_vec() };
        let mut named = BTreeSet::new();
        // Comments name modules in links and prose, not imports.
        let text: String = text.lines().filter(|l| !l.trim_start().starts_with("//")).collect::<Vec<_>>().join("\n");
        for (root, base) in [("crate::", Vec::new()), ("super::", parent.clone())] {
            for (i, _) in text.match_indices(root) {
                if text[..i].ends_with(|c: char| c.is_alphanumeric() || c == '_' || c == ':') {
                    continue;
                }
                let mut path = base.clone();
                let mut rest = &text[i + root.len()..];
                while let Some(seg) = Some(ident(rest)).filter(|s| !s.is_empty()) {
                    path.push(seg.clone());
                    rest = &rest[seg.len()..];
                    match rest.strip_prefix("::") {
                        Some(r) => rest = r,
                        None => break,
                    }
                }
                // `a::{b, c::d}`: each item of one level of braces.
                let mut paths = vec![path.clone()];
                if let Some(inner) = rest.strip_prefix('{').and_then(|r| r.split('}').next()) {
                    paths.extend(inner.split(',').map(|item| path.iter().cloned().chain(item.trim().split("::").map(|s| ident(s.trim()))).filter(|s| !s.is_empty()).collect()));
                }
                named.extend(paths.iter().filter_map(|p| resolve(p)));
            }
        }
        let descendant = |m: &str| m.starts_with(&format!("{module}::"));
        edges.insert(module.clone(), named.into_iter().filter(|m| m != module && !descendant(m)).collect());
    }
    edges
}

#[test]
fn no_two_files_import_each_other() {
    let circles = circles(&file_imports());
    assert!(circles.is_empty(), "import circles between files:\n{}", circles.iter().map(|c| c.join(" -> ")).collect::<Vec<_>>().join("\n"));
}

#[test]
fn file_imports_resolve_to_files() {
    let edges = file_imports();
    // A plain import, a braced one and a `super::` one.
    assert!(edges["passes::recover"].contains("torch::train"), "{:?}", edges["passes::recover"]);
    assert!(edges["passes::recover"].contains("passes::prune"), "{:?}", edges["passes::recover"]);
    assert!(edges["torch::train"].contains("torch::schedule"), "{:?}", edges["torch::train"]);
    assert!(!edges["passes"].iter().any(|m| m.starts_with("passes::")), "a module's own children are not its imports");
}

#[test]
fn a_circle_is_found() {
    let mut edges: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for (a, b) in [("onnx", "ir"), ("ir", "tensor"), ("tensor", "onnx"), ("detect", "metrics")] {
        edges.entry(a.into()).or_default().insert(b.into());
    }
    let c = circles(&edges);
    assert_eq!(c.len(), 3, "{c:?}");
    assert!(c.contains(&vec!["onnx".to_string(), "ir".into(), "tensor".into(), "onnx".into()]), "{c:?}");
}
