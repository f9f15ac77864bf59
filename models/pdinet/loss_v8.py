"""YOLOv8 detection loss: task-aligned assignment, CIoU + distribution focal loss on the
box bins, BCE classes with IoU-aware soft targets.

  L_det = 7.5 L_box + 0.5 L_cls + 1.5 L_dfl  (ultralytics' YOLOv8 hyperparameters)

The assigner follows YOLOv8's TaskAlignedAssigner: an anchor point is a candidate for a box
when its centre lies inside it; the alignment metric s^alpha * IoU^beta (s = the predicted
score of the box's class) picks the top 10 candidates per box; an anchor claimed by several
boxes goes to the one it overlaps most; class targets are one-hot scaled by the normalized
alignment metric.
"""
import torch
import torch.nn.functional as F

from pdinet.boxes import ciou_xyxy, xywh_to_xyxy
from pdinet.model import STRIDES

HYP = dict(box=7.5, cls=0.5, dfl=1.5, topk=10, alpha=0.5, beta=6.0)
PARTS = ("l_box", "l_cls", "l_dfl")
EPS = 1e-9


def anchor_points(feats):
    """Cell centres in grid units [A, 2] and each one's stride [A, 1], P3 first."""
    pts, strides = [], []
    for x, s in zip(feats, STRIDES):
        h, w = x.shape[-2:]
        ys, xs = torch.meshgrid(torch.arange(h, device=x.device) + 0.5, torch.arange(w, device=x.device) + 0.5, indexing="ij")
        pts.append(torch.stack((xs, ys), -1).view(-1, 2).float())
        strides.append(torch.full((h * w, 1), float(s), device=x.device))
    return torch.cat(pts), torch.cat(strides)


def decode_dist(points, dist, reg_max):
    """Box bins [b, A, 4 * reg_max] -> corner boxes in grid units [b, A, 4] (the DFL integral)."""
    b, a, _ = dist.shape
    proj = torch.arange(reg_max, device=dist.device, dtype=dist.dtype)
    ltrb = dist.view(b, a, 4, reg_max).softmax(3) @ proj
    lt, rb = ltrb.chunk(2, -1)
    return torch.cat((points - lt, points + rb), -1)


@torch.no_grad()
def assign(scores, boxes, points, gt_cls, gt_boxes, gt_mask, nc):
    """scores [b, A, nc] (sigmoid), boxes [b, A, 4] px, points [A, 2] px, gt_* [b, n, ...]
    -> target boxes [b, A, 4], target scores [b, A, nc], foreground mask [b, A]."""
    b, n = gt_boxes.shape[:2]
    a = points.shape[0]
    if n == 0:
        return torch.zeros_like(boxes), torch.zeros_like(scores), torch.zeros((b, a), dtype=torch.bool, device=scores.device)
    lt = points[None, None] - gt_boxes[:, :, None, :2]
    rb = gt_boxes[:, :, None, 2:] - points[None, None]
    inside = torch.cat((lt, rb), -1).amin(-1) > EPS  # [b, n, A]
    cand = inside & gt_mask[:, :, None]
    cls_idx = gt_cls.long().clamp(0, nc - 1)  # [b, n]
    box_scores = scores.transpose(1, 2).gather(1, cls_idx[..., None].expand(-1, -1, a))  # [b, n, A]
    overlaps = torch.zeros((b, n, a), device=scores.device, dtype=scores.dtype)
    iou = ciou_xyxy(gt_boxes[:, :, None, :].expand(-1, -1, a, -1)[cand], boxes[:, None].expand(-1, n, -1, -1)[cand])
    overlaps[cand] = iou.clamp(0).to(overlaps.dtype)
    metric = box_scores.pow(HYP["alpha"]) * overlaps.pow(HYP["beta"]) * cand
    top = metric.topk(min(HYP["topk"], a), dim=-1).indices  # [b, n, k]
    pos = torch.zeros_like(metric).scatter_(-1, top, 1.0) * cand * gt_mask[:, :, None]
    multi = pos.sum(1, keepdim=True) > 1  # an anchor claimed by several boxes
    if multi.any():
        best = F.one_hot(overlaps.argmax(1), n).transpose(1, 2).to(pos.dtype)
        pos = torch.where(multi, best, pos)
    fg = pos.sum(1) > 0  # [b, A]
    gt_idx = pos.argmax(1)  # [b, A]
    t_boxes = gt_boxes.gather(1, gt_idx[..., None].expand(-1, -1, 4))
    t_cls = cls_idx.gather(1, gt_idx)
    t_scores = F.one_hot(t_cls, nc).to(scores.dtype) * fg[..., None]
    metric = metric * pos
    norm = (metric * (overlaps * pos).amax(-1, keepdim=True) / (metric.amax(-1, keepdim=True) + EPS)).amax(1)
    return t_boxes, t_scores * norm[..., None], fg


def dfl_loss(dist, target, reg_max):
    """Distribution focal loss: cross-entropy to the two bins around each target distance."""
    target = target.clamp(0, reg_max - 1 - 0.01)
    tl = target.long()
    wl = tl + 1 - target
    ce = lambda t: F.cross_entropy(dist.reshape(-1, reg_max), t.reshape(-1), reduction="none").view(t.shape)
    return (ce(tl) * wl + ce(tl + 1) * (1 - wl)).mean(-1)


def yolo_v8_loss(feats, targets, nc, reg_max, img_wh, normalizer=None):
    """feats: list of [bs, 4 * reg_max + nc, ny, nx]; targets: [n, 6] (img, cls, cx, cy, w, h) normalized.
    `normalizer(target_scores)` divides the terms (default: their sum, at least 1); a
    distributed caller passes the whole batch's."""
    bs, dev = feats[0].shape[0], feats[0].device
    x = torch.cat([f.flatten(2) for f in feats], 2).transpose(1, 2)  # [b, A, no]
    dist, logits = x.split((4 * reg_max, nc), -1)
    points, strides = anchor_points(feats)
    boxes = decode_dist(points, dist, reg_max)  # grid units
    # Targets padded to [b, n_max, ...] in pixels.
    counts = torch.bincount(targets[:, 0].long(), minlength=bs) if targets.shape[0] else torch.zeros(bs, dtype=torch.long, device=dev)
    n = int(counts.max()) if bs else 0
    gt_boxes = torch.zeros((bs, n, 4), device=dev)
    gt_cls = torch.zeros((bs, n), device=dev)
    gt_mask = torch.zeros((bs, n), dtype=torch.bool, device=dev)
    if n:
        img = targets[:, 0].long()
        order = torch.argsort(img, stable=True)
        img, t = img[order], targets[order]
        slot = torch.arange(len(t), device=dev) - torch.cumsum(counts, 0)[img] + counts[img]
        scale = torch.tensor([img_wh[0], img_wh[1], img_wh[0], img_wh[1]], device=dev, dtype=t.dtype)
        gt_boxes[img, slot] = xywh_to_xyxy(t[:, 2:6] * scale)
        gt_cls[img, slot] = t[:, 1]
        gt_mask[img, slot] = True
    t_boxes, t_scores, fg = assign(logits.detach().sigmoid(), boxes.detach() * strides, points * strides, gt_cls, gt_boxes, gt_mask, nc)
    score_sum = normalizer(t_scores) if normalizer is not None else t_scores.sum().clamp(min=1)
    l_cls = F.binary_cross_entropy_with_logits(logits, t_scores, reduction="sum") / score_sum
    l_box = torch.zeros((), device=dev)
    l_dfl = torch.zeros((), device=dev)
    if fg.any():
        w = t_scores.sum(-1)[fg]
        t_grid = t_boxes / strides
        iou = ciou_xyxy(boxes[fg], t_grid[fg])
        l_box = ((1.0 - iou) * w).sum() / score_sum
        pts = points[None].expand(bs, -1, -1)[fg]
        t_ltrb = torch.cat((pts - t_grid[fg][:, :2], t_grid[fg][:, 2:] - pts), -1)
        l_dfl = (dfl_loss(dist[fg], t_ltrb, reg_max) * w).sum() / score_sum
    loss = HYP["box"] * l_box + HYP["cls"] * l_cls + HYP["dfl"] * l_dfl
    return loss * bs, torch.stack((l_box, l_cls, l_dfl)).detach()
