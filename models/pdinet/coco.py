"""COCO bookkeeping for evaluation: labels and detections in COCO form, mAP by pycocotools."""
import contextlib
import io

NUM_CLASSES = 6  # as pdinet.model; kept here so evaluation needs no torch


def coco_map(images, anns, dets):
    """(mAP@0.5, mAP@0.5:0.95) with pycocotools."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    if not dets:
        return 0.0, 0.0
    gt = {"images": images, "annotations": anns, "categories": [{"id": c + 1, "name": str(c)} for c in range(NUM_CLASSES)]}
    with contextlib.redirect_stdout(io.StringIO()):
        cg = COCO()
        cg.dataset = gt
        cg.createIndex()
        e = COCOeval(cg, cg.loadRes(dets), "bbox")
        e.evaluate()
        e.accumulate()
        e.summarize()
    return float(e.stats[1]), float(e.stats[0])


def coco_entries(idx, w, h, labels, xyxy, score, cls, keep, anns, dets):
    """Appends frame idx's labels and kept detections in COCO form."""
    for c, cx, cy, bw, bh in labels:
        anns.append({"id": len(anns) + 1, "image_id": idx + 1, "category_id": int(c) + 1, "bbox": [float((cx - bw / 2) * w), float((cy - bh / 2) * h), float(bw * w), float(bh * h)], "area": float(bw * w * bh * h), "iscrowd": 0})
    for j in keep:
        b = xyxy[j]
        dets.append({"image_id": idx + 1, "category_id": int(cls[j]) + 1, "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])], "score": float(score[j])})
