//! The tree speaks of the project alone: no file names a work-tracker number, narrates who
//! measured what in which sitting, or holds a path of the machine it was written on. Users
//! read these files; what they need is the setting that produced a figure, not its history.

use crate::common::repo;

/// What gives a file away, as (what it is, a predicate on one lowercased line).
fn findings(line: &str) -> Vec<&'static str> {
    let l = line.to_lowercase();
    let mut out = Vec::new();
    let number_after = |word: &str| {
        l.match_indices(word).any(|(at, w)| {
            let before = l[..at].chars().next_back();
            let rest = l[at + w.len()..].trim_start_matches(['#', ' ']);
            !before.is_some_and(|c| c.is_alphanumeric()) && rest.starts_with(|c: char| c.is_ascii_digit())
        })
    };
    if number_after("stop ") || l.match_indices("(#").any(|(at, _)| l[at + 2..].starts_with(|c: char| c.is_ascii_digit())) {
        out.push("a work-tracker number");
    }
    // The tracker's own word: the project has no other use for it.
    if l.split(|c: char| !c.is_alphanumeric()).any(|w| w == "issue" || w == "issues") {
        out.push("a work-tracker item");
    }
    let sittings = ["this session", "a later session", "an earlier session", "earlier sessions", "later session", "last session", "previous session", "project's sessions", "the brief"];
    if sittings.iter().any(|s| l.contains(s)) {
        out.push("narration of how the work was organised");
    }
    if ["/work/", "/root/", "/home/", "/tmp/"].iter().any(|p| l.contains(p)) {
        out.push("a path of one machine");
    }
    out
}

#[test]
fn the_tree_speaks_of_the_project_alone() {
    let files = std::process::Command::new("git").args(["ls-files"]).current_dir(repo()).output().unwrap();
    assert!(files.status.success(), "git ls-files failed");
    let me = "tests/suite/records.rs";
    let mut found = Vec::new();
    for path in String::from_utf8(files.stdout).unwrap().lines().filter(|p| *p != me && !p.ends_with("Cargo.lock") && !p.starts_with("fuzz/corpus/")) {
        let Ok(text) = std::fs::read_to_string(repo().join(path)) else { continue }; // binary
        for (i, line) in text.lines().enumerate() {
            for what in findings(line) {
                found.push(format!("{path}:{}: {what}: {}", i + 1, line.trim().chars().take(100).collect::<String>()));
            }
        }
    }
    assert!(found.is_empty(), "{} line(s):\n{}", found.len(), found.join("\n"));
}

/// The check finds what it is for, and passes what it is not for.
#[test]
fn the_check_tells_narration_from_plain_words() {
    for bad in ["moved here (#49)", "issue 50's CPU line", "as stop 52 measured", "a later session, one run", "clone /work/main", "under the issue's 20", "what the docs issue built"] {
        assert!(!findings(bad).is_empty(), "{bad}");
    }
    for fine in ["[the recommendation](#which-to-deploy)", "an ONNX Runtime session per worker", "tissue 5", "the stop signal", "stop-gradient"] {
        assert!(findings(fine).is_empty(), "{fine}: {:?}", findings(fine));
    }
}
