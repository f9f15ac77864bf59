//! Reading detections out of a head's output tensor.
//!
//! In-graph decoded heads (what ultralytics-style exports produce):
//! - YOLOv5: [1, N, 5 + nc] rows of (cx, cy, w, h, objectness, class probs); score = obj x cls;
//! - YOLOv8: [1, 4 + nc, N] columns of (cx, cy, w, h, class probs); score = cls.

use super::Detection;
use crate::analysis::head::HeadKind;
use crate::tensor::Tensor;
use anyhow::{bail, Result};

/// Candidates above `conf` (one per anchor: its best class, as YOLO validation does with
/// `multi_label=False`).
pub fn candidates(kind: HeadKind, t: &Tensor, conf: f32) -> Result<Vec<Detection>> {
    let Some(v) = t.as_f32() else { bail!("detection output is not float32") };
    let s = &t.shape;
    if s.len() != 3 || s[0] != 1 {
        bail!("detection output has shape {s:?}; expected [1, N, 5+nc] or [1, 4+nc, N]");
    }
    let mut out = Vec::new();
    let mut push = |cx: f32, cy: f32, w: f32, h: f32, class: usize, score: f32| {
        if score > conf && score.is_finite() {
            out.push(Detection { class, score, bbox: [cx - w / 2.0, cy - h / 2.0, cx + w / 2.0, cy + h / 2.0] });
        }
    };
    match kind {
        HeadKind::Yolov5Anchor => {
            let no = s[2];
            if no < 6 {
                bail!("YOLOv5 output rows have {no} values; need 5 + classes");
            }
            for r in v.chunks_exact(no) {
                let (class, p) = argmax(&r[5..]);
                push(r[0], r[1], r[2], r[3], class, r[4] * p);
            }
        }
        HeadKind::Yolov8Dfl => {
            let (ch, n) = (s[1], s[2]);
            if ch < 5 {
                bail!("YOLOv8 output has {ch} channels; need 4 + classes");
            }
            let at = |c: usize, i: usize| v[c * n + i];
            for i in 0..n {
                let (class, p) = (0..ch - 4).map(|c| (c, at(4 + c, i))).fold((0, f32::MIN), |b, x| if x.1 > b.1 { x } else { b });
                push(at(0, i), at(1, i), at(2, i), at(3, i), class, p);
            }
        }
        HeadKind::Raw => bail!("this head has no in-graph decode; raw heads are decoded by the target's post-processing"),
    }
    Ok(out)
}

fn argmax(v: &[f32]) -> (usize, f32) {
    v.iter().enumerate().fold((0, f32::MIN), |b, (i, &x)| if x > b.1 { (i, x) } else { b })
}

/// Channel groups of a detection output, for per-group error: (name, channel range).
pub fn channel_groups(kind: HeadKind, shape: &[usize]) -> Vec<(&'static str, std::ops::Range<usize>)> {
    match (kind, shape) {
        (HeadKind::Yolov5Anchor, [_, _, no]) => vec![("boxes", 0..4), ("objectness", 4..5), ("classes", 5..*no)],
        (HeadKind::Yolov8Dfl, [_, ch, _]) => vec![("boxes", 0..4), ("classes", 4..*ch)],
        _ => vec![],
    }
}
