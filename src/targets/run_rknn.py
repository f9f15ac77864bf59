"""Runs this folder's model on the RK3588's NPU and prints what it detects.

On the board (rknn-toolkit-lite2):   python3 run_rknn.py FRAMES [--out detections.json]
On a PC, the toolkit's simulator:    python3 run_rknn.py FRAMES --simulate [--float]

FRAMES: a frame, a folder of frames, or a numbered sequence (frames/%05d.png); 8/16-bit
PNG/TIFF (colour converted to luma) or .npy in [0, 1]. Pre-processing and decoding follow
rknn.yaml and are those of `pdi-compile run` (its Rust code is the reference): luma in [0, 1]
by the bit depth's full scale, area-resized to the model's frame, the scene's ROI cropped,
replicated into the input's channels, fed as the 8-bit pixels the NPU normalizes by
input.std_values; the split head decoded per stride (YOLOv5 anchors or YOLOv8 DFL) and
class-aware NMS with rknn.yaml's post_processing. --simulate builds the model from model.onnx
with rknn.yaml's quantization (--float: without it) and runs the toolkit's simulator.
Writes COCO results (image_id, file_name, category_id, category_name, bbox xywh, score).
"""
import argparse
import json
import math
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def load_config():
    with open(os.path.join(HERE, "rknn.yaml")) as f:
        text = f.read()
    try:
        import yaml
        return yaml.safe_load(text)
    except ImportError:
        from ruamel.yaml import YAML
        return YAML(typ="safe").load(text)


def frame_files(spec):
    if "%" in spec:
        first = 0 if os.path.isfile(spec % 0) else 1
        out, i = [], first
        while os.path.isfile(spec % i):
            out.append(spec % i)
            i += 1
        if not out:
            sys.exit(f"error: {spec}: no frame of this sequence exists")
        return out
    if os.path.isdir(spec):
        out = sorted(os.path.join(spec, n) for n in os.listdir(spec) if n.lower().endswith((".png", ".tif", ".tiff", ".npy")))
        if not out:
            sys.exit(f"error: {spec}: no frames (PNG, TIFF or .npy files) in this folder")
        return out
    if not os.path.isfile(spec):
        sys.exit(f"error: {spec}: no such frame, folder or sequence")
    return [spec]


def read_luma(path):
    """Luma in [0, 1] as float32 [H, W]: integer images by their full scale."""
    if path.endswith(".npy"):
        a = np.squeeze(np.load(path)).astype(np.float32)
        if a.ndim != 2:
            sys.exit(f"error: {path}: expected a [H, W] array, got {a.shape}")
        return a
    try:
        import cv2
        img = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if img is None:
            sys.exit(f"error: {path}: cannot decode image")
        if img.ndim == 3:
            img = img[:, :, :3][:, :, ::-1]  # BGR(A) -> RGB
    except ImportError:
        from PIL import Image
        img = np.array(Image.open(path))
    if img.dtype == np.uint8:
        v = img.astype(np.float32) / 255.0
    elif img.dtype == np.uint16:
        v = img.astype(np.float32) / 65535.0
    else:
        sys.exit(f"error: {path}: {img.dtype} samples; frames are 8- or 16-bit images or .npy arrays in [0, 1]")
    if v.ndim == 3:  # sRGB luma weights, as the image crate converts colour
        v = v[:, :, 0] * 0.2126 + v[:, :, 1] * 0.7152 + v[:, :, 2] * 0.0722
    return v


def area_weights(s, d):
    scale = s / d
    w = np.zeros((d, s), dtype=np.float64)
    for o in range(d):
        a, b = o * scale, (o + 1) * scale
        for i in range(math.floor(a), min(math.ceil(b), s)):
            w[o, i] = (min(b, i + 1.0) - max(a, float(i))) / scale
    return w.astype(np.float32)


def resize_area(v, w, h):
    """Exact box integration, rows then columns (the Rust resize_area)."""
    sh, sw = v.shape
    if (sh, sw) == (h, w):
        return v
    rows = v @ area_weights(sw, w).T
    return area_weights(sh, h) @ rows


def preprocess(cfg, luma):
    """The NPU's input for one frame: 8-bit pixels, NCHW, float32 (the runtime casts)."""
    _, c, h, w = cfg["input"]["shape"]
    crop = cfg.get("crop")
    fh, fw = crop["frame"] if crop else (h, w)
    v = resize_area(luma, fw, fh)
    if crop:
        x, y, rw, rh = crop["roi"]
        v = v[y:y + rh, x:x + rw]
    pixels = np.round(np.clip(v, 0.0, 1.0) * 255.0).astype(np.float32)
    return np.repeat(pixels[None, None], c, axis=1)


def v5_level(layout, level, boxes, scores, conf, found):
    nc, a_n = layout["classes"], len(level["anchors"])
    hh, ww, s = level["height"], level["width"], float(level["stride"])
    ox, oy = layout.get("offset", [0.0, 0.0])
    b = boxes.reshape(a_n, 4, hh, ww)
    sc = scores.reshape(a_n, 1 + nc, hh, ww)
    for a, (aw, ah) in enumerate(level["anchors"]):
        obj = sc[a, 0]
        ys, xs = np.nonzero(obj > conf)
        for y, x in zip(ys, xs):
            cls = sc[a, 1:, y, x]
            k = int(np.argmax(cls))
            score = float(obj[y, x] * cls[k])
            if score > conf:
                bx = b[a, :, y, x]
                cx = (bx[0] * 2 - 0.5 + x) * s + ox
                cy = (bx[1] * 2 - 0.5 + y) * s + oy
                bw, bh = (bx[2] * 2) ** 2 * aw, (bx[3] * 2) ** 2 * ah
                found.append((k, score, [cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2]))


def v8_level(layout, level, boxes, scores, conf, found):
    nc, reg = layout["classes"], layout.get("reg_max") or 16
    hh, ww, s = level["height"], level["width"], float(level["stride"])
    ox, oy = layout.get("offset", [0.0, 0.0])
    sc = scores.reshape(nc, hh, ww)
    best = sc.max(axis=0)
    ys, xs = np.nonzero(best > conf)
    logits = boxes.reshape(4, reg, hh, ww)
    for y, x in zip(ys, xs):
        k = int(np.argmax(sc[:, y, x]))
        l = logits[:, :, y, x]
        e = np.exp(l - l.max(axis=1, keepdims=True))
        d = (e * np.arange(reg)).sum(axis=1) / e.sum(axis=1)
        ax, ay = x + 0.5, y + 0.5
        x1, y1, x2, y2 = ax - d[0], ay - d[1], ax + d[2], ay + d[3]
        cx, cy, bw, bh = (x1 + x2) / 2 * s + ox, (y1 + y2) / 2 * s + oy, (x2 - x1) * s, (y2 - y1) * s
        found.append((k, float(sc[k, y, x]), [cx - bw / 2, cy - bh / 2, cx + bw / 2, cy + bh / 2]))


def iou(a, b):
    w = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    h = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = w * h
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return 0.0 if union <= 0 else inter / union


def nms(found, thr, max_det):
    kept = []
    for d in sorted(found, key=lambda d: -d[1]):
        if len(kept) >= max_det:
            break
        if all(k[0] != d[0] or iou(k[2], d[2]) <= thr for k in kept):
            kept.append(d)
    return kept


def decode(cfg, outputs, conf):
    layout, post = cfg["head_layout"], cfg["post_processing"]
    found = []
    for level in layout["levels"]:
        boxes, scores = outputs[level["boxes"]], outputs[level["scores"]]
        if layout["kind"] == "yolov5-anchor":
            v5_level(layout, level, boxes, scores, conf, found)
        else:
            v8_level(layout, level, boxes, scores, conf, found)
    return nms(found, post["nms_iou"], post["max_detections"])


def runtime(cfg, simulate, float_model):
    if not simulate:
        from rknnlite.api import RKNNLite
        r = RKNNLite()
        if r.load_rknn(os.path.join(HERE, "model.rknn")) != 0 or r.init_runtime() != 0:
            sys.exit("error: cannot load model.rknn on the NPU (build it with `pdi-compile rknn-convert`)")
        return r
    from rknn.api import RKNN
    r = RKNN(verbose=False)
    q = cfg["quantization"]
    r.config(mean_values=cfg["input"]["mean_values"], std_values=cfg["input"]["std_values"], target_platform=cfg["target_platform"],
             quantized_dtype=q["quantized_dtype"], quantized_algorithm=q["quantized_algorithm"], quantized_method=q["quantized_method"])
    if r.load_onnx(model=os.path.join(HERE, cfg["model"]), outputs=cfg["outputs"]) != 0:
        sys.exit("error: the toolkit cannot load model.onnx")
    cwd = os.getcwd()
    os.chdir(HERE)  # dataset.txt lists paths relative to this folder
    try:
        built = r.build(do_quantization=q["do_quantization"] and not float_model, dataset=q["dataset"])
    finally:
        os.chdir(cwd)
    if built != 0 or r.init_runtime() != 0:
        sys.exit("error: the toolkit could not build or simulate the model")
    return r


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("frames")
    p.add_argument("--out", default="detections.json")
    p.add_argument("--simulate", action="store_true", help="the toolkit's simulator instead of the NPU")
    p.add_argument("--float", action="store_true", help="with --simulate: build without quantization")
    p.add_argument("--conf", type=float, help="score threshold (default: rknn.yaml's post_processing)")
    a = p.parse_args()
    cfg = load_config()
    conf = a.conf if a.conf is not None else cfg["post_processing"]["score_threshold"]
    names = cfg.get("names") or [str(i) for i in range(cfg["head_layout"]["classes"])]
    files = frame_files(a.frames)
    r = runtime(cfg, a.simulate, a.float)
    results = []
    for i, path in enumerate(files):
        luma = read_luma(path)
        fh, fw = cfg["crop"]["frame"] if cfg.get("crop") else cfg["input"]["shape"][2:]
        outs = r.inference(inputs=[preprocess(cfg, luma)], data_format="nchw")
        dets = decode(cfg, dict(zip(cfg["outputs"], [np.asarray(o, dtype=np.float32).reshape(-1) for o in outs])), conf)
        sx, sy = luma.shape[1] / fw, luma.shape[0] / fh
        for k, score, (x1, y1, x2, y2) in dets:
            x1, y1, x2, y2 = x1 * sx, y1 * sy, x2 * sx, y2 * sy
            results.append({"image_id": i + 1, "file_name": os.path.basename(path), "category_id": k, "category_name": names[k] if k < len(names) else str(k),
                            "bbox": [x1, y1, x2 - x1, y2 - y1], "score": score})
        print(f"{os.path.basename(path)}: {len(dets)} detection(s)", file=sys.stderr)
    r.release()
    with open(a.out, "w") as f:
        json.dump(results, f, indent=1)
    print(f"{len(results)} detections in {len(files)} frame(s) -> {a.out}")


if __name__ == "__main__":
    main()
