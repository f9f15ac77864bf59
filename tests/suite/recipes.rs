//! Recipes that compose: `base:` and `without:` expand to the flat pass lists the shipped
//! recipes wrote out before they composed, and compile to the same bytes.

use crate::common::{cli, repo};

const PSF: &str = "calib/single_lwir_blur.npy";
use pdi_compile::pipeline::recipe::{Recipe, SHIPPED};

/// Each shipped recipe's pass list as it was written out before `base:` (2026-11-27, 3b32050),
/// one pass per entry in the recipe's own YAML flow form.
const FLAT: &[(&str, &[&str])] = &[
    ("detect-f32", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "cleanup",
    ]),
    ("detect-fp16", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "cleanup",
        "fp16: {activations: true, calib_frames: 8, headroom: 0.25}",
    ]),
    ("detect-int8", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "cleanup",
        "space-to-depth",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, measured_bias: true, float_head_inputs: true, narrow_float: 16}",
        "narrow-convs-nchw",
    ]),
    ("detect-int8-learned", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "cleanup",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, rounding: learned, rounding_iterations: 400, rounding_frames: 16}",
    ]),
    ("detect-int8-qat", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "cleanup",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, qat: {steps: 800}}",
    ]),
    ("detect-int8-robust", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "cleanup",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, calib_conditions: [gain_x2, offset_+0.15, hot_objects_16px]}",
    ]),
    ("detect-pruned-f32", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {target: {macs: 0.30}, unused_levels: 0.005, max_ratios: {/detect/: 0.5, /enc1/: 0.5, /enc2/body/body.0: 0.5}, importance: l1, round_to: 16, compensate: lstsq, ridge: 0.05}",
        "recover: {steps: 8000, lr: 3.0e-3, batch: 8, frames: 4096}",
        "cleanup",
        "narrow-convs-nchw",
    ]),
    ("detect-pruned-f32-norecover", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {ratio: 0.5, importance: l1, round_to: 8, compensate: lstsq, ridge: 0.05}",
        "cleanup",
        "narrow-convs-nchw",
    ]),
    ("detect-pruned-fp16", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {target: {macs: 0.30}, unused_levels: 0.005, max_ratios: {/detect/: 0.5, /enc1/: 0.5, /enc2/body/body.0: 0.5}, importance: l1, round_to: 16, compensate: lstsq, ridge: 0.05}",
        "recover: {steps: 8000, lr: 3.0e-3, batch: 8, frames: 4096}",
        "cleanup",
        "narrow-convs-nchw",
        "fp16: {activations: true, calib_frames: 8, headroom: 0.25}",
    ]),
    ("detect-pruned-fp16-norecover", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {ratio: 0.5, importance: l1, round_to: 8, compensate: lstsq, ridge: 0.05}",
        "cleanup",
        "narrow-convs-nchw",
        "fp16: {activations: true, calib_frames: 8, headroom: 0.25}",
    ]),
    ("detect-pruned-int8", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {target: {macs: 0.30}, unused_levels: 0.005, max_ratios: {/detect/: 0.5, /enc1/: 0.5, /enc2/body/body.0: 0.5}, importance: l1, round_to: 16, compensate: lstsq, ridge: 0.05}",
        "recover: {steps: 8000, lr: 3.0e-3, batch: 8, frames: 4096}",
        "cleanup",
        "narrow-convs-nchw",
        "space-to-depth",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, float_head_inputs: true, narrow_float: 16}",
        "narrow-convs-nchw",
    ]),
    ("detect-pruned-int8-norecover", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {ratio: 0.5, importance: l1, round_to: 8, compensate: lstsq, ridge: 0.05}",
        "cleanup",
        "narrow-convs-nchw",
        "space-to-depth",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, float_head_inputs: true, narrow_float: 16}",
        "narrow-convs-nchw",
    ]),
    ("detect-pruned-int8-qat", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "resize-to-deconv",
        "dce",
        "prune: {target: {macs: 0.30}, unused_levels: 0.005, max_ratios: {/detect/: 0.5, /enc1/: 0.5, /enc2/body/body.0: 0.5}, importance: l1, round_to: 16, compensate: lstsq, ridge: 0.05}",
        "recover: {steps: 19000, lr: 2.0e-3, batch: 8, frames: 4096}",
        "cleanup",
        "quantize: {method: mse, activations: u8, weight_bits: 7, calib_frames: 64, bias_correction: true, error_budget: 0.1, qat: {teacher: original, steps: 3500, lr: 1.0e-3, frames: 4096}}",
        "narrow-convs-nchw",
    ]),
    ("detect-pruned-rknn", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "dce",
        "prune: {target: {macs: 0.30}, unused_levels: 0.005, max_ratios: {/detect/: 0.5, /enc1/: 0.5, /enc2/body/body.0: 0.5}, importance: l1, round_to: 16, compensate: lstsq, ridge: 0.05}",
        "recover: {steps: 8000, lr: 3.0e-3, batch: 8, frames: 4096}",
        "cleanup",
        "rknn-legalize",
    ]),
    ("detect-pruned-rknn-norecover", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "dce",
        "prune: {ratio: 0.5, importance: l1, round_to: 16, compensate: lstsq, ridge: 0.05}",
        "cleanup",
        "rknn-legalize",
    ]),
    ("detect-rknn", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "dce",
        "cleanup",
        "rknn-legalize",
    ]),
    ("detect-rknn-qat", &[
        "promote-constants",
        "strip-recon",
        "bind-psf",
        "fold-constants",
        "fold-psf-gates",
        "fold-bn",
        "dce",
        "cleanup",
        "rknn-legalize",
        "rknn-qat: {steps: 800}",
    ]),
];

fn flow(spec: &pdi_compile::pipeline::PassSpec) -> yaml_serde::Value {
    match &spec.options {
        yaml_serde::Value::Null => yaml_serde::Value::String(spec.name.clone()),
        o => yaml_serde::Value::Mapping(yaml_serde::Mapping::from_iter([(yaml_serde::Value::String(spec.name.clone()), o.clone())])),
    }
}

#[test]
fn every_recipe_expands_to_the_list_it_wrote_out_before() {
    assert_eq!(FLAT.len(), 17);
    for (name, before) in FLAT {
        let recipe = Recipe::load(&repo().join(format!("passes/{name}.yaml"))).unwrap_or_else(|e| panic!("{name}: {e:#}"));
        let text = std::fs::read_to_string(repo().join(format!("passes/{name}.yaml"))).unwrap();
        assert!(text.contains("base: "), "{name} writes its lossless passes out again");
        let now: Vec<yaml_serde::Value> = recipe.passes.iter().map(flow).collect();
        let was: Vec<yaml_serde::Value> = before.iter().map(|p| yaml_serde::from_str(p).unwrap()).collect();
        assert_eq!(now, was, "{name} expands to another list");
        assert!(!recipe.bases.is_empty(), "{name}: bases recorded");
    }
    // The lossless list is written once, in detect-lossless.
    let mut writers = Vec::new();
    for (name, text) in SHIPPED {
        if text.contains("  - fold-psf-gates") {
            writers.push(*name);
        }
    }
    assert_eq!(writers, ["detect-lossless"]);
}

#[test]
fn the_built_in_recipes_are_the_files() {
    let mut files: Vec<String> = std::fs::read_dir(repo().join("passes"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "yaml") && !["gate.yaml", "stress.yaml"].iter().any(|n| p.ends_with(n)))
        .map(|p| p.file_stem().unwrap().to_string_lossy().into_owned())
        .collect();
    files.sort();
    let mut built: Vec<String> = SHIPPED.iter().map(|r| r.0.to_string()).collect();
    built.sort();
    assert_eq!(files, built, "every recipe under passes/ is built in (src/pipeline/recipe.rs SHIPPED)");
}

#[test]
fn bases_resolve_beside_the_file_then_among_the_shipped_and_refuse_mistakes() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    std::fs::write(d.join("mine.yaml"), "name: mine\nbase: detect-f32\npasses: [quantize]\n").unwrap();
    let r = Recipe::load(&d.join("mine.yaml")).unwrap();
    assert_eq!(r.bases, ["detect-f32", "detect-lossless"]);
    assert_eq!(r.passes.len(), 10, "detect-lossless (8), cleanup, quantize");
    // A sibling of the base's name wins over the shipped one.
    std::fs::write(d.join("detect-f32.yaml"), "name: detect-f32\npasses: [dce]\n").unwrap();
    let r = Recipe::load(&d.join("mine.yaml")).unwrap();
    assert_eq!(r.passes.iter().map(|p| p.name.as_str()).collect::<Vec<_>>(), ["dce", "quantize"]);
    assert_eq!(r.passes[0].at(), "line 2 of base detect-f32: dce");
    for (text, says) in [
        ("name: x\nbase: no-such\npasses: []\n", "no-such"),
        ("name: x\nbase: detect-lossless\nwithout: [quantize]\npasses: []\n", "has no pass quantize"),
        ("name: x\nwithout: [dce]\npasses: []\n", "add `base:`"),
        ("name: x\nbase: x\npasses: []\n", "deeper than"),
        ("name: x\nbase: ../passes/detect-f32\npasses: []\n", "not a path"),
    ] {
        std::fs::write(d.join("x.yaml"), text).unwrap();
        let e = format!("{:#}", Recipe::load(&d.join("x.yaml")).unwrap_err());
        assert!(e.contains(says), "{text}: {e}");
    }
    // On the command line: one line, exit 2, the base named.
    std::fs::write(d.join("x.yaml"), "name: x\nbase: detect-f3\npasses: []\n").unwrap();
    let r = cli(&["compile", "models/trained/pdinet_v5_tiny_trained.onnx", "--pipeline", d.join("x.yaml").to_str().unwrap(), "--psf", PSF, "-o", d.join("out").to_str().unwrap()]);
    assert_eq!(r.code, 2, "{}", r.stderr);
    assert!(r.stderr.contains("base 'detect-f3'") && r.stderr.trim().lines().count() == 1, "{}", r.stderr);
}

/// The flat recipes and the composed ones compile a fixture to the same bytes, and the
/// manifest records the expanded list.
#[test]
fn composed_recipes_compile_to_the_same_models() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let model = "models/fixtures/pdinet_v5_input_op17_nofold.onnx";
    for name in ["detect-f32", "detect-rknn", "detect-pruned-f32-norecover"] {
        let before = FLAT.iter().find(|r| r.0 == name).unwrap().1;
        let flat = d.join(format!("{name}.flat.yaml"));
        std::fs::write(&flat, format!("name: {name}\npasses:\n{}", before.iter().map(|p| format!("  - {p}\n")).collect::<String>())).unwrap();
        let (a, b) = (d.join(format!("{name}.a")), d.join(format!("{name}.b")));
        for (recipe, out) in [(flat.to_str().unwrap().to_string(), &a), (format!("passes/{name}.yaml"), &b)] {
            let r = cli(&["compile", model, "--pipeline", &recipe, "--psf", PSF, "-o", out.to_str().unwrap()]);
            assert_eq!(r.code, 0, "{name}: {}", r.stderr);
        }
        assert!(std::fs::read(a.join("model.onnx")).unwrap() == std::fs::read(b.join("model.onnx")).unwrap(), "{name}: the composed recipe compiles another model");
        let manifest = std::fs::read_to_string(b.join("manifest.yaml")).unwrap();
        assert!(manifest.contains("fold-psf-gates"), "{name}: the manifest records the expanded list: {manifest}");
    }
}

/// Every shipped recipe reads, names itself after its file, and each of its passes accepts
/// its options (unknown ones are errors), so a recipe is never first found broken by a user.
#[test]
fn every_shipped_recipe_builds() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("passes");
    let mut seen = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "yaml") || ["gate.yaml", "stress.yaml"].iter().any(|n| path.ends_with(n)) {
            continue;
        }
        let recipe = pdi_compile::pipeline::Recipe::load(&path).unwrap_or_else(|e| panic!("{}: {e:#}", path.display()));
        assert_eq!(Some(recipe.name.as_str()), path.file_stem().and_then(|s| s.to_str()), "{}", path.display());
        for spec in &recipe.passes {
            if let Err(e) = pdi_compile::pipeline::build_pass(spec) {
                panic!("{}: pass {}: {e:#}", path.display(), spec.name);
            }
        }
        seen += 1;
    }
    assert!(seen >= 18, "only {seen} recipes in {}", dir.display());
}
