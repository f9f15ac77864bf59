//! docs/reference/ is what the code generates: a pass option's default, a doc comment, a flag
//! or a recipe changed without `scripts/reference` fails here.

use crate::common::repo;

#[test]
fn the_committed_reference_is_what_the_code_generates() {
    let dir = repo().join("docs/reference");
    let pages = pdi_compile::reference::pages().unwrap();
    for (name, text) in &pages {
        let committed = std::fs::read_to_string(dir.join(name)).unwrap_or_default();
        if &committed != text {
            let line = committed.lines().zip(text.lines()).position(|(a, b)| a != b).unwrap_or(committed.lines().count().min(text.lines().count()));
            panic!("docs/reference/{name} differs from what the code generates from line {} on (committed: {:?}, generated: {:?}): run scripts/reference", line + 1, committed.lines().nth(line), text.lines().nth(line));
        }
    }
    let mut files: Vec<String> = std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    files.sort();
    let mut names: Vec<String> = pages.iter().map(|p| p.0.clone()).collect();
    names.sort();
    assert_eq!(files, names, "docs/reference/ holds exactly the generated pages");
}

/// Every option of every pass says what it does.
#[test]
fn every_pass_option_is_documented() {
    let passes = pdi_compile::reference::pages().unwrap().into_iter().find(|p| p.0 == "passes.md").unwrap().1;
    let mut pass = "";
    let mut bare = Vec::new();
    for line in passes.lines() {
        if let Some(p) = line.strip_prefix("## ") {
            pass = p;
        } else if line.starts_with("| `") && line.ends_with("|  |") {
            bare.push(format!("{pass} {}", line.split('|').nth(1).unwrap().trim()));
        }
    }
    assert!(bare.is_empty(), "options without a doc comment: {bare:?}");
}

