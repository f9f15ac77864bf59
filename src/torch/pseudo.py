"""The teacher's detections as labels for the student, scored with YOLOv8's own loss
(`pdinet/loss_v8.py`: task-aligned assignment, CIoU and DFL on the boxes, BCE on IoU-aware
class targets), beside the distillation of the head's outputs.

Distillation matches every cell's distributions; the detector's loss ranks them: each object's
best-aligned cells are to score highest and to put their boxes on the teacher's, which is what
mAP reads after NMS keeps one box an object.
"""
import torch

from pdinet.loss_v8 import anchor_points, decode_dist, yolo_v8_loss

# The teacher's boxes kept as labels: score above CONF, then class-aware NMS at IoU NMS_IOU
# (YOLOv8's validation IoU), at most MAX_PER_FRAME.
CONF = 0.25
NMS_IOU = 0.7
MAX_PER_FRAME = 100


def levels(ts, heads):
    """The YOLOv8 levels as (box head index, class head index), finest first, or [] when the
    heads are not a YOLOv8 head's per-level box and class convolutions."""
    boxes = [i for i, h in enumerate(heads) if h["kind"] == "v8box"]
    classes = [i for i, h in enumerate(heads) if h["kind"] == "v8cls"]
    pairs = []
    for b in boxes:
        c = [c for c in classes if ts[c].shape[2:] == ts[b].shape[2:]]
        if len(c) != 1:
            return []
        pairs.append((b, c[0]))
    return sorted(pairs, key=lambda p: -ts[p[0]].shape[2])


def iou_matrix(a, b):
    """Plain IoU of corner boxes a [n, 4] against b [m, 4]: [n, m]."""
    lt = torch.maximum(a[:, None, :2], b[None, :, :2])
    rb = torch.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = (rb - lt).clamp(min=0).prod(-1)
    area = lambda x: (x[:, 2:] - x[:, :2]).clamp(min=0).prod(-1)
    return inter / (area(a)[:, None] + area(b)[None] - inter).clamp(min=1e-9)


def nms(boxes, scores, classes, iou):
    """Indices kept by greedy class-aware NMS, best first."""
    order = scores.argsort(descending=True)
    # Boxes of different classes never overlap once shifted apart by class.
    shifted = boxes[order] + classes[order, None].to(boxes.dtype) * (boxes.max() + 1)
    over = iou_matrix(shifted, shifted) > iou
    alive = torch.ones(len(order), dtype=torch.bool, device=boxes.device)
    keep = []
    for i in range(len(order)):
        if alive[i]:
            keep.append(i)
            alive &= ~over[i]
    return order[keep]


@torch.no_grad()
def labels(feats, nc, reg_max):
    """The teacher's detections on each frame as YOLO labels [n, 6] (frame, class, cx, cy, w,
    h normalized), and the frame's size in pixels (w, h)."""
    x = torch.cat([f.flatten(2) for f in feats], 2).transpose(1, 2)
    dist, logits = x.split((4 * reg_max, nc), -1)
    points, strides = anchor_points(feats)
    boxes = decode_dist(points, dist, reg_max) * strides
    best, cls = logits.sigmoid().max(-1)
    h, w = feats[0].shape[2] * int(strides[0]), feats[0].shape[3] * int(strides[0])
    scale = torch.tensor([w, h], dtype=boxes.dtype, device=boxes.device)
    rows = []
    for b in range(x.shape[0]):
        sel = (best[b] > CONF).nonzero().flatten()
        sel = sel[best[b, sel].argsort(descending=True)[:4 * MAX_PER_FRAME]]
        if len(sel) == 0:
            continue
        k = sel[nms(boxes[b, sel], best[b, sel], cls[b, sel], NMS_IOU)[:MAX_PER_FRAME]]
        xyxy = boxes[b, k]
        centre, size = (xyxy[:, :2] + xyxy[:, 2:]) / 2 / scale, (xyxy[:, 2:] - xyxy[:, :2]) / scale
        rows.append(torch.cat((torch.full((len(k), 1), float(b), device=x.device), cls[b, k, None].to(x.dtype), centre, size), 1))
    found = torch.cat(rows) if rows else torch.zeros((0, 6), device=x.device)
    return found, (w, h)


def per_level(vs, pairs):
    """Each level's box and class values as one [B, 4 * reg_max + nc, H, W] map, finest first."""
    return [torch.cat((vs[b], vs[c]), 1) for b, c in pairs]


def loss(ss, ts, heads, normalizer):
    """YOLOv8's loss of the student's head outputs `ss` against the teacher's detections
    (from `ts`), per frame of the batch; None when the heads are not YOLOv8's."""
    pairs = levels(ts, heads)
    if not pairs:
        return None
    reg_max, nc = heads[pairs[0][0]]["reg_max"], ts[pairs[0][1]].shape[1]
    student = per_level(ss, pairs)
    found, size = labels(per_level(ts, pairs), nc, reg_max)
    total, _ = yolo_v8_loss(student, found, nc, reg_max, size, normalizer)
    return total / student[0].shape[0]
