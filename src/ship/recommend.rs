//! Which artifact to deploy on each target, by measurement: on a CPU engine, the fastest
//! variant that keeps `min_kept` of the original's mAP (against labels when the frames have
//! them, else the agreement with its detections), as the tract target keeps INT8 only where it
//! runs faster; on the RK3588, the RKNN folder (INT8 is what the NPU runs).

use super::Variant;
use serde::Serialize;
use std::path::Path;

#[derive(Serialize, Debug, Clone, PartialEq)]
pub struct Recommendation {
    /// `onnxruntime`, `tract` or `rk3588`.
    pub target: String,
    /// The variant's name, or none when no variant qualifies.
    pub variant: Option<String>,
    /// Why, in one line.
    pub why: String,
}

/// What share of the original's accuracy `v` keeps, and what it is measured as.
fn kept(v: &Variant, original: &Variant) -> Option<(f64, &'static str)> {
    match (v.map_labels, original.map_labels) {
        (Some(m), Some(o)) if o > 0.0 => Some((m / o, "mAP")),
        _ => v.agreement.map(|a| (a, "agreement")),
    }
}

/// A kept share as the screen shows it: two decimals, or three where two would print the bar
/// itself for a share on either side of it (0.896 is not "0.90x" beside "at least 0.90x").
fn share(k: f64, bar: f64) -> String {
    let two = format!("{k:.2}");
    if two == format!("{bar:.2}") && k != bar {
        format!("{k:.3}x")
    } else {
        format!("{two}x")
    }
}

pub fn recommend(variants: &[Variant], min_kept: f64, rknn: &Path, rknn_failed: bool) -> Vec<Recommendation> {
    let mut out = Vec::new();
    let Some(original) = variants.first() else { return out };
    for (target, engine) in [("onnxruntime", "ORT"), ("tract", "tract")] {
        let ms = |v: &Variant| if engine == "ORT" { v.ort_ms } else { v.tract_ms };
        let candidates: Vec<(&Variant, f64, f64, &str)> = variants.iter().skip(1).filter_map(|v| { let (k, what) = kept(v, original)?; Some((v, ms(v)?, k, what)) }).collect();
        let good = candidates.iter().filter(|c| c.2 >= min_kept).min_by(|a, b| a.1.total_cmp(&b.1));
        let fastest = candidates.iter().min_by(|a, b| a.1.total_cmp(&b.1));
        let r = match (good, fastest) {
            (Some(&(v, t, k, what)), Some(&(f, ft, fk, fwhat))) => {
                let mut why = format!("{t:.2} ms on {engine}, keeps {} of the original's {what}: the fastest of those keeping at least {min_kept:.2}x", share(k, min_kept));
                if f.name != v.name {
                    why.push_str(&format!(" ({} runs in {ft:.2} ms but keeps {} of the {fwhat})", f.name, share(fk, min_kept)));
                }
                if let Some(slower) = candidates.iter().filter(|c| c.0.name != v.name && c.1 > t && c.2 <= k).map(|c| c.0.name.as_str()).next() {
                    why.push_str(&format!("; {slower} is slower and no more accurate"));
                }
                Recommendation { target: target.into(), variant: Some(v.name.clone()), why }
            }
            (None, Some(&(f, ft, fk, fwhat))) => Recommendation {
                target: target.into(),
                variant: None,
                why: format!("no artifact keeps {min_kept:.2}x of the original's {fwhat} (the fastest, {}, runs in {ft:.2} ms and keeps {}): recover longer (--recover-steps) or deploy the original", f.name, share(fk, min_kept)),
            },
            _ => Recommendation { target: target.into(), variant: None, why: format!("nothing was measured on {engine}") },
        };
        out.push(r);
    }
    out.push(if rknn_failed {
        Recommendation { target: "rk3588".into(), variant: None, why: "the RKNN folder failed to build (see above)".into() }
    } else {
        Recommendation {
            target: "rk3588".into(),
            variant: Some("rknn".into()),
            why: format!("INT8 is what the NPU runs; build and check it on the toolkit's simulator: pdi-compile rknn-convert {}", rknn.display()),
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn v(name: &str, ort: f64, tract: f64, map: f64) -> Variant {
        Variant { name: name.into(), folder: String::new(), file: String::new(), bytes: 0, macs: 0, params: 0, ort_ms: Some(ort), tract_ms: Some(tract), map_labels: Some(map), agreement: Some(1.0), agreement_tract: None, compile_seconds: 0.0, note: None }
    }

    #[test]
    fn the_fastest_that_keeps_enough_and_why() {
        // The demo's measurements (2026-11-27): INT8 slower and less accurate than pruned-f32.
        let vs = [v("original", 11.44, 20.0, 0.4534), v("f32", 11.69, 16.34, 0.4534), v("pruned-f32", 4.29, 8.20, 0.4200), v("pruned-int8", 15.26, 13.15, 0.4100)];
        let r = recommend(&vs, 0.9, Path::new("out/rknn"), false);
        assert_eq!(r[0].variant.as_deref(), Some("pruned-f32"), "{r:?}");
        assert!(r[0].why.contains("pruned-int8 is slower and no more accurate"), "{}", r[0].why);
        assert_eq!(r[1].variant.as_deref(), Some("pruned-f32"));
        assert_eq!(r[2].variant.as_deref(), Some("rknn"));
        // With 800 recovery steps the pruned model keeps 0.78x: the lossless one is recommended.
        let vs = [v("original", 11.44, 20.0, 0.4534), v("f32", 11.69, 16.34, 0.4534), v("pruned-f32", 4.29, 8.20, 0.3539), v("pruned-int8", 15.26, 13.15, 0.3345)];
        let r = recommend(&vs, 0.9, Path::new("out/rknn"), false);
        assert_eq!(r[0].variant.as_deref(), Some("f32"));
        assert!(r[0].why.contains("pruned-f32 runs in 4.29 ms but keeps 0.78x"), "{}", r[0].why);
        let r = recommend(&vs, 0.99, Path::new("out/rknn"), true);
        assert_eq!(r[0].variant.as_deref(), Some("f32"), "the lossless compile keeps 1.00x");
        assert_eq!(r[2].variant, None);
        let r = recommend(&vs[..1], 0.9, Path::new("out/rknn"), false);
        assert_eq!(r[0].variant, None);
        // A share that two decimals would print as the bar gets a third.
        let vs = [v("original", 11.44, 20.0, 0.4534), v("f32", 11.69, 16.34, 0.4534), v("pruned-f32", 4.29, 8.20, 0.4062)];
        let r = recommend(&vs, 0.9, Path::new("out/rknn"), false);
        assert_eq!(r[0].variant.as_deref(), Some("f32"));
        assert!(r[0].why.contains("pruned-f32 runs in 4.29 ms but keeps 0.896x of the mAP"), "{}", r[0].why);
        assert_eq!((share(0.9, 0.9), share(0.904, 0.9), share(0.95, 0.9)), ("0.90x".into(), "0.904x".into(), "0.95x".into()));
    }
}
