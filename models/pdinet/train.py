"""Train a tiny PDI-Net (YOLOv5 head) with the paper's joint loss on physics-pipeline frames.

  L_total = 0.01 L_rec + 1.0 L_det,  L_det = 0.05 L_box + 1.0 L_obj + 0.5 L_cls,  SGD lr 0.01

Input: a dataset made by `pdi-compile dataset` (clean/ = ground truth for L_rec, degraded/ =
the q=90 single-lens frames the network sees, YOLO labels beside both). Frames are simulated
on the 640x480 sensor (so the PSFs have their physical pixel size) and area-downscaled to the
training size here; YOLO labels are normalized, so they carry over unchanged.

  python pdinet/train.py --data /tmp/pdi-train --eval /tmp/pdi-eval --out trained --epochs 40
"""
import argparse
import json
import math
import os
import sys
import time

import numpy as np
import torch
import torch.nn.functional as F
from PIL import Image

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from pdinet.model import PDINet, STRIDES  # noqa: E402

HYP = dict(rec=0.01, det=1.0, box=0.05, obj=1.0, cls=0.5, anchor_t=4.0, lr=0.01, momentum=0.937, wd=5e-4)
OBJ_BALANCE = (4.0, 1.0, 0.4)  # P3, P4, P5 (ultralytics)


def load_split(root, size):
    """(degraded, clean, labels) from root/degraded and root/clean, downscaled to size (W, H)."""
    names = sorted(f for f in os.listdir(os.path.join(root, "degraded")) if f.endswith(".png"))
    raw, gt, labels = [], [], []
    for n in names:
        def img(sub):
            im = Image.open(os.path.join(root, sub, n))
            a = np.asarray(im, dtype=np.float32) / 65535.0
            return np.asarray(Image.fromarray(a, mode="F").resize(size, Image.BOX), dtype=np.float32)
        raw.append(img("degraded"))
        gt.append(img("clean"))
        lp = os.path.join(root, "degraded", n[:-4] + ".txt")
        rows = np.loadtxt(lp, ndmin=2) if os.path.getsize(lp) else np.zeros((0, 5))
        labels.append(rows.astype(np.float32).reshape(-1, 5))
    return np.stack(raw)[:, None], np.stack(gt)[:, None], labels


def bbox_ciou(b1, b2, eps=1e-7):
    """CIoU of xywh boxes (rows)."""
    (x1, y1, w1, h1), (x2, y2, w2, h2) = b1.T, b2.T
    b1x1, b1x2, b1y1, b1y2 = x1 - w1 / 2, x1 + w1 / 2, y1 - h1 / 2, y1 + h1 / 2
    b2x1, b2x2, b2y1, b2y2 = x2 - w2 / 2, x2 + w2 / 2, y2 - h2 / 2, y2 + h2 / 2
    inter = (torch.min(b1x2, b2x2) - torch.max(b1x1, b2x1)).clamp(0) * (torch.min(b1y2, b2y2) - torch.max(b1y1, b2y1)).clamp(0)
    union = w1 * h1 + w2 * h2 - inter + eps
    iou = inter / union
    cw = torch.max(b1x2, b2x2) - torch.min(b1x1, b2x1)
    ch = torch.max(b1y2, b2y2) - torch.min(b1y1, b2y1)
    c2 = cw ** 2 + ch ** 2 + eps
    rho2 = ((x2 - x1) ** 2 + (y2 - y1) ** 2)
    v = (4 / math.pi ** 2) * (torch.atan(w2 / (h2 + eps)) - torch.atan(w1 / (h1 + eps))) ** 2
    with torch.no_grad():
        alpha = v / (v - iou + (1 + eps))
    return iou - (rho2 / c2 + v * alpha)


def yolo_loss(preds, targets, anchors, nc):
    """YOLOv5 loss. preds: list of [bs, na, ny, nx, 5+nc]; targets: [n, 6] (img, cls, cx, cy, w, h) normalized."""
    dev = preds[0].device
    lbox, lobj, lcls = torch.zeros(1, device=dev), torch.zeros(1, device=dev), torch.zeros(1, device=dev)
    g = 0.5
    off = torch.tensor([[0, 0], [1, 0], [0, 1], [-1, 0], [0, -1]], device=dev).float() * g
    na = anchors.shape[1]
    for i, p in enumerate(preds):
        bs, _, ny, nx, _ = p.shape
        anc = anchors[i] / STRIDES[i]  # anchors in grid units
        tobj = torch.zeros(p.shape[:4], device=dev)
        if targets.shape[0]:
            gain = torch.tensor([1, 1, nx, ny, nx, ny], device=dev).float()
            t = targets * gain  # to grid units
            t = t[None].repeat(na, 1, 1)  # [na, n, 6]
            ai = torch.arange(na, device=dev).float().view(na, 1).repeat(1, targets.shape[0])
            r = t[..., 4:6] / anc[:, None]
            j = torch.max(r, 1 / r).max(2)[0] < HYP["anchor_t"]
            t, ai = t[j], ai[j]
            gxy = t[:, 2:4]
            gxi = torch.tensor([nx, ny], device=dev) - gxy
            jx, ky = ((gxy % 1 < g) & (gxy > 1)).T
            lx, my = ((gxi % 1 < g) & (gxi > 1)).T
            sel = torch.stack((torch.ones_like(jx), jx, ky, lx, my))
            t = t.repeat((5, 1, 1))[sel]
            ai = ai.repeat((5, 1))[sel]
            offsets = (torch.zeros_like(gxy)[None] + off[:, None])[sel]
            b, c = t[:, 0].long(), t[:, 1].long()
            gxy = t[:, 2:4]
            gij = (gxy - offsets).long()
            gi, gj = gij[:, 0].clamp(0, nx - 1), gij[:, 1].clamp(0, ny - 1)
            a = ai.long()
            ps = p[b, a, gj, gi]
            if ps.shape[0]:
                pxy = ps[:, :2].sigmoid() * 2 - 0.5
                pwh = (ps[:, 2:4].sigmoid() * 2) ** 2 * anc[a]
                tbox = torch.cat((gxy - gij.float(), t[:, 4:6]), 1)
                iou = bbox_ciou(torch.cat((pxy, pwh), 1), tbox)
                lbox += (1.0 - iou).mean()
                tobj[b, a, gj, gi] = iou.detach().clamp(0).type(tobj.dtype)
                tc = torch.zeros_like(ps[:, 5:])
                tc[range(ps.shape[0]), c] = 1.0
                lcls += F.binary_cross_entropy_with_logits(ps[:, 5:], tc)
        lobj += F.binary_cross_entropy_with_logits(p[..., 4], tobj) * OBJ_BALANCE[i]
    bs = preds[0].shape[0]
    return (HYP["box"] * lbox + HYP["obj"] * lobj + HYP["cls"] * lcls) * bs, torch.cat((lbox, lobj, lcls)).detach()


def nms_numpy(boxes, scores, classes, iou_thr=0.6, max_det=300):
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


def evaluate(model, raw, labels, psf, size, conf=0.001):
    """COCO mAP with pycocotools on the eval split (same decode + class-aware NMS as pdi-compile)."""
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval
    import contextlib
    import io

    model.eval()
    w, h = size
    images, anns, dets = [], [], []
    with torch.no_grad():
        for i0 in range(0, len(raw), 16):
            x = torch.from_numpy(raw[i0:i0 + 16])
            _, out = model(x, psf.expand(x.shape[0], -1, -1, -1))
            for k, o in enumerate(out.numpy()):
                idx = i0 + k
                images.append({"id": idx + 1, "width": w, "height": h})
                for lab in labels[idx]:
                    c, cx, cy, bw, bh = lab
                    anns.append({"id": len(anns) + 1, "image_id": idx + 1, "category_id": int(c) + 1, "bbox": [float((cx - bw / 2) * w), float((cy - bh / 2) * h), float(bw * w), float(bh * h)], "area": float(bw * w * bh * h), "iscrowd": 0})
                cls = o[:, 5:].argmax(1)
                score = o[:, 4] * o[np.arange(len(o)), 5 + cls]
                m = score > conf
                xywh, score, cls = o[m, :4], score[m], cls[m]
                xyxy = np.concatenate([xywh[:, :2] - xywh[:, 2:] / 2, xywh[:, :2] + xywh[:, 2:] / 2], 1)
                for j in nms_numpy(xyxy, score, cls):
                    b = xyxy[j]
                    dets.append({"image_id": idx + 1, "category_id": int(cls[j]) + 1, "bbox": [float(b[0]), float(b[1]), float(b[2] - b[0]), float(b[3] - b[1])], "score": float(score[j])})
    model.train()
    if not dets:
        return 0.0, 0.0
    gt = {"images": images, "annotations": anns, "categories": [{"id": c + 1, "name": str(c)} for c in range(6)]}
    with contextlib.redirect_stdout(io.StringIO()):
        cg = COCO()
        cg.dataset = gt
        cg.createIndex()
        cd = cg.loadRes(dets)
        e = COCOeval(cg, cd, "bbox")
        e.evaluate()
        e.accumulate()
        e.summarize()
    return float(e.stats[1]), float(e.stats[0])


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--eval", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--psf", required=True, help="blur map .npy [6, 8] of the camera the frames were degraded with")
    ap.add_argument("--size", default="256x192")
    ap.add_argument("--width", type=float, default=0.125)
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--minutes", type=float, default=40.0, help="stop early when the time budget runs out")
    a = ap.parse_args()
    torch.manual_seed(a.seed)
    np.random.seed(a.seed)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    size = tuple(int(v) for v in a.size.split("x"))
    raw, gt, labels = load_split(a.data, size)
    eraw, _, elabels = load_split(a.eval, size)
    psf = torch.from_numpy(np.load(a.psf).astype(np.float32)).view(1, 1, 6, 8)
    model = PDINet(head="v5", width=a.width)
    anchors = model.detect.anchors
    g_bn, g_w, g_b = [], [], []
    for mod in model.modules():
        for n, p in mod.named_parameters(recurse=False):
            (g_b if n == "bias" else g_bn if isinstance(mod, torch.nn.BatchNorm2d) else g_w).append(p)
    opt = torch.optim.SGD([{"params": g_bn}, {"params": g_w, "weight_decay": HYP["wd"]}, {"params": g_b}], lr=HYP["lr"], momentum=HYP["momentum"], nesterov=True)
    n = len(raw)
    steps = a.epochs * math.ceil(n / a.batch)
    warm = max(100, math.ceil(n / a.batch))
    lf = lambda s: (1 - s / steps) * 0.99 + 0.01  # linear decay to 1% (ultralytics lrf)
    t0, step, log = time.time(), 0, []
    model.train()
    for ep in range(a.epochs):
        perm = np.random.permutation(n)
        tot = np.zeros(4)
        for i0 in range(0, n, a.batch):
            idx = perm[i0:i0 + a.batch]
            x, y = torch.from_numpy(raw[idx]), torch.from_numpy(gt[idx])
            tl = []
            flip = np.random.rand(len(idx)) < 0.5
            for k, j in enumerate(idx):
                lab = labels[j].copy()
                if flip[k]:
                    lab[:, 1] = 1 - lab[:, 1]
                tl.append(np.concatenate([np.full((len(lab), 1), k, np.float32), lab], 1))
            if flip.any():
                fi = torch.from_numpy(np.where(flip)[0])
                x[fi], y[fi] = x[fi].flip(-1), y[fi].flip(-1)
            targets = torch.from_numpy(np.concatenate(tl)) if tl else torch.zeros((0, 6))
            lr_scale = lf(step) * min(1.0, (step + 1) / warm)
            for gi, grp in enumerate(opt.param_groups):
                grp["lr"] = HYP["lr"] * lr_scale
            recon, preds = model(x, psf.expand(len(idx), -1, -1, -1))
            l_rec = F.mse_loss(recon, y)
            l_det, parts = yolo_loss(preds, targets, anchors, 6)
            loss = HYP["rec"] * l_rec + HYP["det"] * l_det
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            step += 1
            tot += np.array([l_rec.item(), *parts.numpy()])
        nb = math.ceil(n / a.batch)
        elapsed = (time.time() - t0) / 60
        rec = {"epoch": ep + 1, "minutes": round(elapsed, 2), "l_rec": tot[0] / nb, "l_box": tot[1] / nb, "l_obj": tot[2] / nb, "l_cls": tot[3] / nb}
        if (ep + 1) % 5 == 0 or ep + 1 == a.epochs:
            rec["map50"], rec["map50_95"] = evaluate(model, eraw, elabels, psf, size)
        log.append(rec)
        print(json.dumps(rec), flush=True)
        if elapsed > a.minutes:
            print(f"time budget of {a.minutes} min reached after epoch {ep + 1}", flush=True)
            if "map50" not in rec:
                rec["map50"], rec["map50_95"] = evaluate(model, eraw, elabels, psf, size)
            break
    os.makedirs(a.out, exist_ok=True)
    torch.save(model.state_dict(), os.path.join(a.out, "pdinet_v5_tiny.pt"))
    model.eval()
    path = os.path.join(a.out, "pdinet_v5_tiny_trained.onnx")
    torch.onnx.export(model, (torch.from_numpy(eraw[:1]), psf), path, input_names=["image", "psf_blur"], output_names=["recon", "detections"], opset_version=17, do_constant_folding=True, dynamo=False)
    from pdinet.export import add_metadata
    add_metadata(path, "v5", "input", a.width, size)
    final = log[-1]
    json.dump({"log": log, "final": final, "args": vars(a), "hyp": HYP, "train_frames": n, "eval_frames": len(eraw), "minutes": round((time.time() - t0) / 60, 2)}, open(os.path.join(a.out, "training.json"), "w"), indent=1)
    print(f"final mAP@0.5 {final['map50']:.4f} mAP@0.5:0.95 {final['map50_95']:.4f} -> {path}")


if __name__ == "__main__":
    main()
