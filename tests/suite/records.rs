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
            let rest = l[at + w.len()..].trim_start_matches(['#', ' ', '-']);
            !before.is_some_and(|c| c.is_alphanumeric()) && rest.starts_with(|c: char| c.is_ascii_digit())
        })
    };
    if number_after("stop") || l.match_indices("(#").any(|(at, _)| l[at + 2..].starts_with(|c: char| c.is_ascii_digit())) {
        out.push("a work-tracker number");
    }
    // The tracker's own word: the project has no other use for it.
    if l.split(|c: char| !c.is_alphanumeric()).any(|w| w == "issue" || w == "issues") {
        out.push("a work-tracker item");
    }
    // Written in parts, so that this file does not hold what it looks for.
    let sitting = ["this", "a later", "an earlier", "earlier", "later", "last", "previous", "project's"].iter().any(|w| l.contains(&format!("{w} {}", "session")));
    let tooling = ["brief".to_string(), format!("device {}", "tool"), format!("{} library", "tool")];
    if sitting || tooling.iter().any(|w| l.contains(&format!("the {w}"))) {
        out.push("narration of how the work was organised");
    }
    if ["work", "root", "home", "tmp"].iter().any(|d| l.contains(&format!("/{d}/"))) {
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
    let bad = [format!("moved here ({}49)", '#'), format!("{} 50's CPU line", "issue"), format!("as {} 52 measured", "stop"), format!("the {}-52 runs", "stop"), format!("a later {}, one run", "session"), format!("clone /{}/main", "work"), format!("the device {}'s carry", "tool"), format!("what the docs {} built", "issue")];
    for bad in &bad {
        assert!(!findings(bad).is_empty(), "{bad}");
    }
    // Written in parts too: words that contain or sit beside the tracker's words.
    let fine = ["[the recommendation](#which-to-deploy)".to_string(), format!("an ONNX Runtime {} per worker", "session"), format!("t{} 5", "issue"), format!("the {} signal", "stop"), format!("{}-gradient", "stop")];
    for fine in &fine {
        assert!(findings(fine).is_empty(), "{fine}: {:?}", findings(fine));
    }
}
