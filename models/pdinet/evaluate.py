"""mAP of an exported PDI-Net ONNX on a labelled frame folder, with ONNX Runtime and pycocotools.

Decode and NMS match `pdi-compile verify` (score = obj x best class, conf 0.001, class-aware NMS
at IoU 0.6, 300 detections), so both tools report the same numbers.

  python pdinet/evaluate.py --model trained/pdinet_v5_tiny_trained.onnx --data /tmp/pdi-eval-256/degraded --psf ../calib/single_lwir_blur.npy
"""
import argparse
import contextlib
import io
import json
import os
import sys

import numpy as np
import onnxruntime as ort
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from pdinet.train import nms_numpy  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True, help="folder of 16-bit PNG frames with YOLO .txt labels")
    ap.add_argument("--psf", help="blur map .npy for models that take psf_blur as an input")
    a = ap.parse_args()
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    s = ort.InferenceSession(a.model, providers=["CPUExecutionProvider"])
    names = [i.name for i in s.get_inputs()]
    files = sorted(f for f in os.listdir(a.data) if f.endswith(".png"))
    images, anns, dets = [], [], []
    for idx, f in enumerate(files):
        x = np.asarray(Image.open(os.path.join(a.data, f)), dtype=np.float32)[None, None] / 65535.0
        h, w = x.shape[2:]
        feeds = {"image": x}
        if "psf_blur" in names:
            feeds["psf_blur"] = np.load(a.psf).astype(np.float32).reshape(1, 1, 6, 8)
        out = s.run(["detections"], feeds)[0][0]
        images.append({"id": idx + 1, "width": w, "height": h})
        lp = os.path.join(a.data, f[:-4] + ".txt")
        for lab in (np.loadtxt(lp, ndmin=2) if os.path.getsize(lp) else np.zeros((0, 5))):
            c, cx, cy, bw, bh = lab
            anns.append({"id": len(anns) + 1, "image_id": idx + 1, "category_id": int(c) + 1, "bbox": [(cx - bw / 2) * w, (cy - bh / 2) * h, bw * w, bh * h], "area": bw * w * bh * h, "iscrowd": 0})
        cls = out[:, 5:].argmax(1)
        score = out[:, 4] * out[np.arange(len(out)), 5 + cls]
        m = score > 0.001
        xywh, score, cls = out[m, :4], score[m], cls[m]
        xyxy = np.concatenate([xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2], 1)
        for j in nms_numpy(xyxy, score, cls):
            b = xyxy[j]
            dets.append({"image_id": idx + 1, "category_id": int(cls[j]) + 1, "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])], "score": float(score[j])})
    gt = {"images": images, "annotations": anns, "categories": [{"id": c + 1, "name": str(c)} for c in range(6)]}
    with contextlib.redirect_stdout(io.StringIO()):
        cg = COCO()
        cg.dataset = gt
        cg.createIndex()
        e = COCOeval(cg, cg.loadRes(dets), "bbox")
        e.evaluate()
        e.accumulate()
        e.summarize()
    print(json.dumps({"frames": len(files), "objects": len(anns), "map50": round(float(e.stats[1]), 4), "map50_95": round(float(e.stats[0]), 4)}))


if __name__ == "__main__":
    main()
