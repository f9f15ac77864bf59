//! `pdi-compile-fuzz TARGET`: one AFL++ harness for every target of
//! `pdi_compile::fuzz_targets` (onnx, recipe, scene, gate, conditions, npy, image).

fn main() {
    let name = std::env::args().nth(1).unwrap_or_default();
    let Some(&(_, target)) = pdi_compile::fuzz_targets::TARGETS.iter().find(|(n, _)| *n == name) else {
        let names: Vec<&str> = pdi_compile::fuzz_targets::TARGETS.iter().map(|(n, _)| *n).collect();
        eprintln!("usage: pdi-compile-fuzz TARGET (one of {})", names.join(", "));
        std::process::exit(2);
    };
    afl::fuzz!(|data: &[u8]| target(data));
}
