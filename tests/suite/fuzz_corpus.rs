//! Replays what the fuzzers saved: every corpus entry (seeded from the fixtures, grown by
//! `scripts/fuzz`) and every crash input they found, through the same targets. A crash
//! input stays here after its fix, so the bug cannot come back unnoticed.

use pdi_compile::fuzz_targets::TARGETS;
use std::path::Path;

fn inputs(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut v: Vec<_> = std::fs::read_dir(dir).map(|d| d.filter_map(|e| e.ok().map(|e| e.path())).filter(|p| p.is_file()).collect()).unwrap_or_default();
    v.sort();
    v
}

#[test]
fn every_saved_fuzz_input_is_answered_without_a_panic() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz");
    for (name, target) in TARGETS {
        let corpus = inputs(&root.join("corpus").join(name));
        assert!(corpus.len() >= 3, "fuzz/corpus/{name} holds {} inputs; run scripts/fuzz to seed it", corpus.len());
        let crashes = inputs(&root.join("crashes").join(name));
        for path in corpus.iter().chain(&crashes) {
            let data = std::fs::read(path).unwrap();
            // A panic fails this test and names the input.
            let r = std::panic::catch_unwind(|| target(&data));
            assert!(r.is_ok(), "{name}: {} panics", path.display());
        }
        println!("{name}: {} corpus inputs, {} crash inputs replayed", corpus.len(), crashes.len());
    }
}
