//! A pass written outside the registry, run by the same runner: what adding a pass takes
//! (docs/design.md). It scales every graph output by a constant, warns when asked to scale by
//! one, and leaves a teacher as a structural pass would.

use super::*;
use pdi_compile::passes::{Capability, Pass};
use pdi_compile::pipeline::PassReport;

struct ScaleOutputs {
    factor: f32,
}

impl Pass for ScaleOutputs {
    fn name(&self) -> &'static str {
        "scale-outputs"
    }

    fn check(&self) -> anyhow::Result<()> {
        anyhow::ensure!(self.factor.is_finite(), "scale-outputs: factor must be finite");
        Ok(())
    }

    fn provides(&self) -> Vec<Capability> {
        vec![Capability::Teacher]
    }

    fn run(&self, model: &mut ModelProto, cx: &mut PassContext) -> anyhow::Result<serde_json::Value> {
        if self.factor == 1.0 {
            cx.warn("a factor of 1 changes nothing");
        }
        let before = model.clone();
        let g = model.graph.as_mut().unwrap();
        // Names no earlier run of the pass took.
        let k = format!("scale_outputs.k{}", g.node.len());
        g.initializer.push(init(&k, vec![1], vec![self.factor]));
        for o in g.output.iter_mut() {
            let raw = format!("{}.unscaled{}", o.name, g.node.len());
            for n in g.node.iter_mut() {
                for out in n.output.iter_mut().filter(|v| **v == o.name) {
                    *out = raw.clone();
                }
            }
            let mut mul = node("Mul", &[&raw, &k], &o.name, vec![]);
            mul.name = format!("scale_outputs.{raw}");
            g.node.push(mul);
        }
        cx.record_cut(|| before, &Default::default());
        Ok(serde_json::json!({ "scaled": g.output.len() }))
    }
}

#[test]
fn a_pass_outside_the_registry_runs_with_its_report_warnings_and_teacher() {
    let mut m = model(vec![node("Relu", &["x"], "y", vec![])], vec![vi("x", &[1, 4])], vec![vi("y", &[1, 4])], vec![]);
    let inputs = vec![input("x", vec![1, 4], 8)];
    let before = outputs(Engine::Ort, &m, &inputs);
    let mut cx = PassContext::default();
    let reports: Vec<PassReport> = pipeline::run_passes(vec![Box::new(ScaleOutputs { factor: 1.0 }), Box::new(ScaleOutputs { factor: 3.0 })], &mut m, &mut cx).unwrap();
    assert_eq!(ops(&m), ["Relu", "Mul", "Mul"]);
    assert_eq!(reports[0].details["scaled"], 1);
    assert_eq!(reports[0].warnings, ["scale-outputs: a factor of 1 changes nothing"]);
    assert!(reports[1].warnings.is_empty());
    assert_eq!((reports[1].before.nodes, reports[1].after.nodes), (2, 3), "the runner counts before and after");
    // The first run left the teacher (the model before it); the second kept it.
    assert_eq!(cx.teacher.as_ref().map(|t| ops(&t.model)), Some(vec!["Relu".to_string()]));
    let after = outputs(Engine::Ort, &m, &inputs);
    let expected: Vec<f32> = before[0].1.as_f32().unwrap().iter().map(|v| v * 3.0).collect();
    assert_eq!(after[0].1.as_f32().unwrap(), &expected[..]);
    // A bad option is refused before anything runs.
    let Err(err) = pipeline::run_passes(vec![Box::new(ScaleOutputs { factor: f32::NAN })], &mut m, &mut cx) else { panic!("a NaN factor ran") };
    assert!(format!("{err:#}").contains("factor must be finite"), "{err:#}");
}
