"""mAP of an exported PDI-Net ONNX on a labelled frame folder, with ONNX Runtime and pycocotools.

Decode and NMS match `pdi-compile verify` and `run` (score = objectness x best class for
YOLOv5, best class for YOLOv8; conf 0.001, class-aware NMS at ultralytics' validation IoU, 0.6
for YOLOv5 and 0.7 for YOLOv8, 300 detections), so the tools report the same numbers; written
in numpy apart from the Rust code, it is what the test suite checks `run`'s detections against.
The head comes from the model's `pdinet.head` metadata.

  python pdinet/evaluate.py --model trained/pdinet_v5_tiny_trained.onnx --data out/pdi-eval-256/degraded --psf ../calib/single_lwir_blur.npy

`--breakdown` adds mAP at each IoU threshold and by object size: where a compiled model's
mAP@0.5:0.95 goes.
"""
import argparse
import json
import os
import sys

import numpy as np
import onnxruntime as ort
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from pdinet.postprocess import candidates, nms_numpy  # noqa: E402
from pdinet.coco import coco_breakdown, coco_entries, coco_map  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True, help="folder of 16-bit PNG frames with YOLO .txt labels")
    ap.add_argument("--psf", help="blur map .npy for models that take psf_blur as an input")
    ap.add_argument("--iou", type=float, help="NMS IoU (default: 0.7 for YOLOv8, 0.6 for YOLOv5)")
    ap.add_argument("--detections", help="also write the detections here (COCO results, xywh, with file_name)")
    ap.add_argument("--breakdown", action="store_true", help="also mAP at each IoU threshold and by object size")
    a = ap.parse_args()
    s = ort.InferenceSession(a.model, providers=["CPUExecutionProvider"])
    head = s.get_modelmeta().custom_metadata_map.get("pdinet.head", "v5")
    iou = a.iou if a.iou is not None else (0.7 if head == "v8" else 0.6)
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
        labels = np.loadtxt(lp, ndmin=2) if os.path.getsize(lp) else np.zeros((0, 5))
        xyxy, score, cls = candidates(out, head)
        first = len(dets)
        coco_entries(idx, w, h, labels, xyxy, score, cls, nms_numpy(xyxy, score, cls, iou), anns, dets)
        for d in dets[first:]:
            d["file_name"] = f
    m50, m5095 = coco_map(images, anns, dets)
    if a.detections:
        with open(a.detections, "w") as out:
            json.dump(dets, out)
    report = {"model": os.path.basename(a.model), "head": head, "iou": iou, "frames": len(files), "objects": len(anns), "map50": round(m50, 4), "map50_95": round(m5095, 4)}
    if a.breakdown:
        report.update(coco_breakdown(images, anns, dets))
    print(json.dumps(report))

if __name__ == "__main__":
    main()
