"""COCO bookkeeping for evaluation: labels and detections in COCO form, mAP by pycocotools."""
import contextlib
import io

NUM_CLASSES = 6  # as pdinet.model; kept here so evaluation needs no torch


def coco_map(images, anns, dets):
    """(mAP@0.5, mAP@0.5:0.95) with pycocotools."""
    if not dets:
        return 0.0, 0.0
    e = _evaluated(images, anns, dets)
    return float(e.stats[1]), float(e.stats[0])


def coco_breakdown(images, anns, dets):
    """Where mAP@0.5:0.95 is lost: mAP at each IoU threshold (0.50, 0.55, ... 0.95) and
    mAP@0.5:0.95 by COCO's object sizes (small below 32x32 pixels, large above 96x96), -1
    where nothing was there to score."""
    if not dets:
        return {}
    e = _evaluated(images, anns, dets)
    p = e.eval["precision"][:, :, :, 0, 2]  # [IoU, recall, class], area "all", 100 detections
    at = [float(p[t][p[t] > -1].mean()) if (p[t] > -1).any() else -1.0 for t in range(p.shape[0])]
    return {"map_at_iou": dict(zip((f"{t:.2f}" for t in e.params.iouThrs), (round(v, 4) for v in at))),
            "map_by_size": {k: round(float(v), 4) for k, v in zip(("small", "medium", "large"), e.stats[3:6])}}


def _evaluated(images, anns, dets):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    gt = {"images": images, "annotations": anns, "categories": [{"id": c + 1, "name": str(c)} for c in range(NUM_CLASSES)]}
    with contextlib.redirect_stdout(io.StringIO()):
        cg = COCO()
        cg.dataset = gt
        cg.createIndex()
        e = COCOeval(cg, cg.loadRes(dets), "bbox")
        e.evaluate()
        e.accumulate()
        e.summarize()
    return e


def coco_entries(idx, w, h, labels, xyxy, score, cls, keep, anns, dets):
    """Appends frame idx's labels and kept detections in COCO form."""
    for c, cx, cy, bw, bh in labels:
        anns.append({"id": len(anns) + 1, "image_id": idx + 1, "category_id": int(c) + 1, "bbox": [float((cx - bw / 2) * w), float((cy - bh / 2) * h), float(bw * w), float(bh * h)], "area": float(bw * w * bh * h), "iscrowd": 0})
    for j in keep:
        b = xyxy[j]
        dets.append({"image_id": idx + 1, "category_id": int(cls[j]) + 1, "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])], "score": float(score[j])})
