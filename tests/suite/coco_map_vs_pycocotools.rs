//! Our COCO mAP equals pycocotools' COCOeval on the same boxes (within 1e-3, as required;
//! in practice to float precision).

use crate::common::Lcg;
use pdi_compile::detect::Detection;
use pdi_compile::metrics::coco_map::{coco_map, Truth};

/// Random scenes: boxes on a quarter-pixel grid so JSON carries them exactly; detections are
/// jittered copies of the truths plus false positives, some with tied scores.
fn scenes(seed: u64, images: usize, classes: usize) -> (Vec<Vec<Truth>>, Vec<Vec<Detection>>) {
    let mut r = Lcg(seed);
    let q = |v: f32| (v * 4.0).round() / 4.0;
    let (mut truths, mut dets) = (Vec::new(), Vec::new());
    for _ in 0..images {
        let (mut ts, mut ds) = (Vec::new(), Vec::new());
        for _ in 0..(r.next_f32() * 8.0) as usize {
            let (x, y) = (q(r.next_f32() * 600.0), q(r.next_f32() * 440.0));
            let (w, h) = (q(4.0 + r.next_f32() * 80.0), q(4.0 + r.next_f32() * 60.0));
            let class = (r.next_f32() * classes as f32) as usize % classes;
            ts.push(Truth { class, bbox: [x, y, x + w, y + h] });
            if r.next_f32() < 0.85 {
                let mut j = |v: f32, s: f32| q(v + (r.next_f32() - 0.5) * s);
                let b = [j(x, w * 0.3), j(y, h * 0.3), j(x + w, w * 0.3), j(y + h, h * 0.3)];
                if b[2] > b[0] && b[3] > b[1] {
                    let c = if r.next_f32() < 0.9 { class } else { (class + 1) % classes };
                    ds.push(Detection { class: c, score: (r.next_f32() * 20.0).round() / 20.0 + 0.01, bbox: b });
                }
            }
        }
        for _ in 0..(r.next_f32() * 4.0) as usize {
            let (x, y) = (q(r.next_f32() * 600.0), q(r.next_f32() * 440.0));
            ds.push(Detection { class: (r.next_f32() * classes as f32) as usize % classes, score: r.next_f32() * 0.5, bbox: [x, y, x + q(5.0 + r.next_f32() * 40.0), y + q(5.0 + r.next_f32() * 40.0)] });
        }
        truths.push(ts);
        dets.push(ds);
    }
    (truths, dets)
}

fn pycocotools(truths: &[Vec<Truth>], dets: &[Vec<Detection>], classes: usize, dir: &std::path::Path) -> (f64, f64) {
    let xywh = |b: &[f32; 4]| vec![b[0] as f64, b[1] as f64, (b[2] - b[0]) as f64, (b[3] - b[1]) as f64];
    let mut anns = Vec::new();
    for (i, ts) in truths.iter().enumerate() {
        for t in ts {
            let b = xywh(&t.bbox);
            anns.push(serde_json::json!({"id": anns.len() + 1, "image_id": i + 1, "category_id": t.class + 1, "bbox": b, "area": b[2] * b[3], "iscrowd": 0}));
        }
    }
    let gt = serde_json::json!({
        "images": (0..truths.len()).map(|i| serde_json::json!({"id": i + 1, "width": 640, "height": 480})).collect::<Vec<_>>(),
        "categories": (0..classes).map(|c| serde_json::json!({"id": c + 1, "name": format!("c{c}")})).collect::<Vec<_>>(),
        "annotations": anns,
    });
    let res: Vec<_> = dets.iter().enumerate().flat_map(|(i, ds)| ds.iter().map(move |d| serde_json::json!({"image_id": i + 1, "category_id": d.class + 1, "bbox": xywh(&d.bbox), "score": d.score as f64}))).collect();
    std::fs::write(dir.join("gt.json"), gt.to_string()).unwrap();
    std::fs::write(dir.join("dt.json"), serde_json::Value::Array(res).to_string()).unwrap();
    let script = "import sys, contextlib, io\nfrom pycocotools.coco import COCO\nfrom pycocotools.cocoeval import COCOeval\nwith contextlib.redirect_stdout(io.StringIO()):\n    g = COCO(sys.argv[1]); d = g.loadRes(sys.argv[2]); e = COCOeval(g, d, 'bbox'); e.evaluate(); e.accumulate(); e.summarize()\nprint(e.stats[0], e.stats[1])\n";
    let python = std::env::var("PDI_PYTHON").expect("PDI_PYTHON is not set: run the suite with scripts/test, which installs pycocotools");
    let out = std::process::Command::new(python).args(["-c", script, dir.join("gt.json").to_str().unwrap(), dir.join("dt.json").to_str().unwrap()]).output().unwrap();
    assert!(out.status.success(), "pycocotools failed: {}", String::from_utf8_lossy(&out.stderr));
    let text = String::from_utf8(out.stdout).unwrap();
    let v: Vec<f64> = text.split_whitespace().map(|s| s.parse().unwrap()).collect();
    (v[0], v[1])
}

#[test]
fn map_matches_pycocotools() {
    let dir = tempfile::tempdir().unwrap();
    for (seed, images, classes) in [(1, 40, 6), (2, 7, 3), (3, 120, 6)] {
        let (truths, dets) = scenes(seed, images, classes);
        let ours = coco_map(&truths, &dets, classes);
        let (py_5095, py_50) = pycocotools(&truths, &dets, classes, dir.path());
        assert!((ours.map50_95 - py_5095).abs() < 1e-3, "seed {seed}: mAP@.5:.95 ours {} pycocotools {py_5095}", ours.map50_95);
        assert!((ours.map50 - py_50).abs() < 1e-3, "seed {seed}: mAP@.5 ours {} pycocotools {py_50}", ours.map50);
        println!("seed {seed}: ours {:.6}/{:.6} pycocotools {py_5095:.6}/{py_50:.6}", ours.map50_95, ours.map50);
        assert!(ours.map50 > 0.2 && ours.map50 < 0.99, "the scenes exercise both matches and misses: {}", ours.map50);
    }
}
