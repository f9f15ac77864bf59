//! The README's results table, its demo screen and the docs/results pages' record blocks are
//! rendered from docs/results/records/ (scripts/results): a figure typed into them, or a record
//! changed without rendering, fails here.

use crate::common::repo;
use std::path::Path;
use std::process::Command;

/// The Python of the cache's environment, which the pages' renderer runs in.
fn python() -> Command {
    Command::new(std::env::var("PDI_PYTHON").expect("PDI_PYTHON is not set: run the suite with scripts/test"))
}

fn check(root: &Path) -> std::process::Output {
    python().arg(repo().join("scripts/results.py")).arg("check").arg(root).output().unwrap()
}

/// `check` on `root`, which must find the pages stale: what it said on stderr.
fn stale(root: &Path) -> String {
    let out = check(root);
    let said = String::from_utf8_lossy(&out.stderr).into_owned();
    assert_eq!(out.status.code(), Some(1), "{said}");
    said
}

/// The pages, records, README and recipes of the repository (a record's block says which of
/// its recipes changed since it ran), copied where a test may change them.
fn copy(to: &Path) {
    let root = repo();
    std::fs::create_dir_all(to.join("docs/results/records")).unwrap();
    std::fs::create_dir_all(to.join("passes")).unwrap();
    std::fs::copy(root.join("README.md"), to.join("README.md")).unwrap();
    for dir in ["docs/results", "docs/results/records", "passes"] {
        for e in std::fs::read_dir(root.join(dir)).unwrap() {
            let e = e.unwrap();
            if e.file_type().unwrap().is_file() {
                std::fs::copy(e.path(), to.join(dir).join(e.file_name())).unwrap();
            }
        }
    }
}

#[test]
fn the_committed_pages_are_what_the_records_render() {
    let out = check(&repo());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn a_record_that_changes_makes_the_pages_stale() {
    let dir = tempfile::tempdir().unwrap();
    copy(dir.path());
    let records = dir.path().join("docs/results/records");
    let first = std::fs::read_dir(&records).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "json")).min().expect("at least one record");
    let text = std::fs::read_to_string(&first).unwrap();
    // Every record carries its date, and every rendering shows it.
    let changed = text.replacen("\"date\": \"", "\"date\": \"1999-", 1);
    assert_ne!(changed, text);
    std::fs::write(&first, changed).unwrap();
    assert!(stale(dir.path()).contains("differs from its records"));
}

#[test]
fn a_figure_typed_into_the_readme_table_is_caught() {
    let dir = tempfile::tempdir().unwrap();
    copy(dir.path());
    let readme = dir.path().join("README.md");
    let text = std::fs::read_to_string(&readme).unwrap();
    let row = text.find("<!-- results table -->").expect("the README holds the results table");
    let at = row + text[row..].find("| lossless").expect("a lossless row");
    let changed = format!("{}| lossless compile, typed by hand | 1.000× | here |\n{}", &text[..at], &text[at..]);
    std::fs::write(&readme, changed).unwrap();
    let said = stale(dir.path());
    assert!(said.contains("README.md differs"), "{said}");
}

#[test]
fn a_recipe_that_computes_something_else_since_its_record_is_named() {
    let dir = tempfile::tempdir().unwrap();
    copy(dir.path());
    let recipe = dir.path().join("passes/detect-int8.yaml");
    let text = std::fs::read_to_string(&recipe).unwrap();
    // Its description's wording changes no byte of what it builds: the pages stand.
    std::fs::write(&recipe, text.replacen("description: >\n", "description: >\n  Reworded.\n", 1)).unwrap();
    let out = check(dir.path());
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    // An option does: every record that ran it now reads as the recipe that was.
    let changed = text.replacen("calib_frames: 64", "calib_frames: 65", 1);
    assert_ne!(changed, text, "detect-int8 no longer sets calib_frames: 64; update this test");
    std::fs::write(&recipe, changed).unwrap();
    let said = stale(dir.path());
    assert!(said.contains("README.md differs"), "{said}");
}

/// A README row that reads one record per model names the stale one, not only the first's:
/// here the v5's record ran a `detect-pruned-f32` that computed something else, the v8's (and
/// its seed-1 run's) the checkout's.
#[test]
fn a_row_of_two_records_names_the_one_whose_recipe_changed() {
    let dir = tempfile::tempdir().unwrap();
    copy(dir.path());
    let script = r#"
import json, sys
from pathlib import Path
root = Path(sys.argv[2]); sys.path.insert(0, sys.argv[1])
import results_render as r
now = r.digests(r.shipped(root))
for name, recipes in (("pruned-v5-w0.25", dict(now, **{"detect-pruned-f32": "computed-else"})), ("pruned-v8-w0.25", now), ("seed1-v8-w0.25", now)):
    path = root / "docs/results/records" / f"{name}.json"
    record = json.loads(path.read_text()); record["recipes"] = recipes
    path.write_text(json.dumps(record))
r.write(root)
"#;
    let out = python().arg("-c").arg(script).arg(repo().join("scripts")).arg(dir.path()).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let readme = std::fs::read_to_string(dir.path().join("README.md")).unwrap();
    let row = readme.lines().find(|l| l.starts_with("| prune + recover")).expect("the pruned records' row");
    assert!(row.ends_with("(`pruned-v5-w0.25`: recipe changed since: `detect-pruned-f32`) |"), "{row}");
    assert!(!row.contains("pruned-v8-w0.25"), "{row}");
}
