"""Post-processing as `pdi-compile verify` does it: decoded rows to scored candidates, class-aware NMS."""
import numpy as np


def nms_numpy(boxes, scores, classes, iou_thr=0.6, max_det=300):
    """Class-aware greedy NMS, the same rule as `pdi-compile verify` (indices, best first)."""
    order = np.argsort(-scores, kind="stable")
    keep = []
    for i in order:
        if len(keep) >= max_det:
            break
        ok = True
        for k in keep:
            if classes[k] != classes[i]:
                continue
            xx1, yy1 = max(boxes[i, 0], boxes[k, 0]), max(boxes[i, 1], boxes[k, 1])
            xx2, yy2 = min(boxes[i, 2], boxes[k, 2]), min(boxes[i, 3], boxes[k, 3])
            inter = max(0.0, xx2 - xx1) * max(0.0, yy2 - yy1)
            a = (boxes[i, 2] - boxes[i, 0]) * (boxes[i, 3] - boxes[i, 1]) + (boxes[k, 2] - boxes[k, 0]) * (boxes[k, 3] - boxes[k, 1]) - inter
            if a > 0 and inter / a > iou_thr:
                ok = False
                break
        if ok:
            keep.append(i)
    return keep


def candidates(out, head, conf=0.001):
    """Decoded rows of one frame -> (xyxy, score, class) above `conf`.

    v5 rows are [N, 5 + nc] (xywh, objectness, classes; score = objectness x best class);
    v8 comes as [4 + nc, N] (xywh, class scores; score = best class)."""
    if head == "v8":
        out = out.T
        cls = out[:, 4:].argmax(1)
        score = out[np.arange(len(out)), 4 + cls]
    else:
        cls = out[:, 5:].argmax(1)
        score = out[:, 4] * out[np.arange(len(out)), 5 + cls]
    m = score > conf
    xywh, score, cls = out[m, :4], score[m], cls[m]
    xyxy = np.concatenate([xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2], 1)
    return xyxy, score, cls
