//! Dependencies point down: each top-level module of `src/` has a layer, and a module imports
//! only from its own layer or below. The imports that still point up are listed in `UPWARD`
//! to be removed (issue 47); the test fails on any new one, and on a listed one that is gone
//! (so the list only shrinks), and on a module that has no layer.

use crate::common::repo;
use std::collections::{BTreeMap, BTreeSet};

/// Lowest first. Modules in one layer may import each other.
const LAYERS: &[&[&str]] = &[
    &["tensor", "fsutil", "warn", "canvas"],
    &["onnx", "ir"],
    &["analysis", "metrics", "detect", "optics", "inspect"],
    &["runtime", "frames", "dataset", "calib_frames", "pyenv"],
    // analyses and rewrites
    &["prune", "quant", "scene", "targets"],
    &["passes"],
    &["pipeline"],
    // libraries the commands share: running an artifact, comparing two models, the manifest
    &["deploy", "verify", "manifest"],
    // commands
    &["compile", "rebuild", "run", "ship", "bench", "stress", "cli", "fuzz_targets", "reference"],
];

/// Imports that point up today, (from, to).
const UPWARD: &[(&str, &str)] = &[
    ("runtime", "passes"),
    ("prune", "passes"),
    ("prune", "pipeline"),
    ("quant", "passes"),
    ("quant", "verify"),
    ("scene", "passes"),
    ("scene", "pipeline"),
    ("scene", "verify"),
    ("targets", "passes"),
    ("targets", "verify"),
    ("passes", "pipeline"),
    ("passes", "stress"),
    ("passes", "verify"),
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
    let mut upward = BTreeSet::new();
    for (from, tos) in &edges {
        let Some(lf) = layer(from) else {
            problems.push(format!("src/{from} has no layer: add it to LAYERS"));
            continue;
        };
        for to in tos {
            let Some(lt) = layer(to) else { continue };
            if lt > lf {
                upward.insert((from.as_str(), to.as_str()));
                if !UPWARD.contains(&(from.as_str(), to.as_str())) {
                    problems.push(format!("{from} (layer {lf}) imports {to} (layer {lt}): a new import that points up"));
                }
            }
        }
    }
    for (from, to) in UPWARD {
        if !upward.contains(&(*from, *to)) {
            problems.push(format!("{from} no longer imports {to}: remove it from UPWARD"));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    // The modules the map names exist: a stale name would hide a module that lost its layer.
    for m in LAYERS.iter().flat_map(|l| l.iter()) {
        assert!(edges.contains_key(*m), "LAYERS names src/{m}, which does not exist");
    }
}
