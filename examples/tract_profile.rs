//! Where tract spends its time on a model: per op kind, over a few runs, on N threads.
//!   cargo run --release --example tract_profile -- MODEL.onnx THREADS [RUNS]
use pdi_compile::runtime::tract_runtime::typed_model;
use std::collections::HashMap;
use std::time::Instant;
use tract_onnx::prelude::*;
use tract_onnx::tract_hir::tract_core::plan::{eval, SimplePlan};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let model = pdi_compile::onnx::io::load(std::path::Path::new(&args[1]))?.model;
    let threads: usize = args[2].parse()?;
    let runs: usize = args.get(3).map_or(Ok(3), |s| s.parse())?;
    let g = model.graph.as_ref().unwrap();
    let input = &g.input[0];
    let shape = pdi_compile::ir::shapes::declared(input).static_shape().unwrap();
    let frame = pdi_compile::calib_frames::calibration_frames(None, 1, shape[2], shape[3], 0)?.frames.remove(0).image;
    let (typed, _, _) = typed_model(&model, &[(input.name.clone(), frame.clone())])?;
    let opt = typed.into_optimized()?;
    let exec = if threads > 1 { tract_linalg::multithread::Executor::multithread(threads) } else { tract_linalg::multithread::Executor::SingleThread };
    let plan = SimplePlan::new_with_options(opt, &RunOptions { executor: Some(exec), ..Default::default() })?;
    let input_t = tract_onnx::prelude::Tensor::from_shape(&frame.shape, frame.as_f32().unwrap())?;
    let mut by_op: HashMap<String, (f64, usize)> = HashMap::new();
    let mut total = 0.0;
    for r in 0..runs + 1 {
        let mut state = plan.spawn()?;
        let t0 = Instant::now();
        let mut times: Vec<(String, f64)> = Vec::new();
        state.run_plan_with_eval(tvec![input_t.clone().into_tvalue()], |ctx, st, node, inputs| {
            let t = Instant::now();
            let out = eval(ctx, st, node, inputs);
            let key = if std::env::var_os("BY_NODE").is_some() { format!("{} {}", node.op().name(), node.name) } else { format!("{}", node.op().name()) };
            times.push((key, t.elapsed().as_secs_f64() * 1e3));
            out
        })?;
        if r > 0 {
            total += t0.elapsed().as_secs_f64() * 1e3;
            for (op, ms) in times {
                let e = by_op.entry(op).or_insert((0.0, 0));
                e.0 += ms;
                e.1 += 1;
            }
        }
    }
    let mut v: Vec<_> = by_op.into_iter().collect();
    v.sort_by(|a, b| b.1 .0.total_cmp(&a.1 .0));
    println!("total {:.1} ms per run ({threads} threads)", total / runs as f64);
    for (op, (ms, n)) in v.iter().take(25) {
        println!("{:>9.1} ms  {:>5}  {op}", ms / runs as f64, n / runs);
    }
    Ok(())
}
