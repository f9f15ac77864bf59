//! Dependencies point down: each top-level module of `src/` has a layer, and a module imports
//! only from its own layer or below; no two modules import each other, directly or through
//! others (a circle within a layer is a circle too); `passes` is imported only by the
//! pipeline and the commands. The test fails on an import that breaks any of these, and on a
//! module that has no layer.

use crate::common::repo;
use std::collections::{BTreeMap, BTreeSet};

/// Lowest first. Modules in one layer may import each other.
const LAYERS: &[&[&str]] = &[
    &["tensor", "fsutil", "warn", "canvas", "clock"],
    &["onnx", "ir"],
    &["analysis", "metrics", "detect", "optics", "inspect"],
    &["runtime", "frames", "dataset", "calib_frames", "pyenv", "torch"],
    // analyses and rewrites
    &["prune", "quant", "scene", "targets"],
    &["passes"],
    &["pipeline"],
    // libraries the commands share: running an artifact, comparing two models, the manifest
    &["deploy", "verify", "manifest"],
    // commands
    &["compile", "rebuild", "run", "ship", "bench", "stress", "cli", "fuzz_targets", "reference"],
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
