"""Train PDI-Net (YOLOv5 or YOLOv8 head) with the paper's joint loss on physics-pipeline frames.

  L_total = 0.01 L_rec + 1.0 L_det,  SGD lr 0.01 (momentum 0.937, Nesterov, weight decay 5e-4)
  L_det: v5 = 0.05 L_box + 1.0 L_obj + 0.5 L_cls (loss_v5.py)
         v8 = 7.5 L_box + 0.5 L_cls + 1.5 L_dfl  (loss_v8.py)

Input: a dataset made by `pdi-compile dataset` (clean/ = ground truth for L_rec, degraded/ =
the frames the network sees, YOLO labels beside both), at the training size or larger (then
area-downscaled here; YOLO labels are normalized, so they carry over unchanged).

Interruptible: a checkpoint (model, optimizer, step, log, elapsed time) is written atomically
after every epoch, and `--resume` continues from it. Each epoch's order and flips come from a
generator seeded by (seed, epoch), so a resumed run sees the same batches as an uninterrupted
one. `--device auto` trains on a CUDA GPU when one is present.

  python pdinet/train.py --head v8 --width 0.25 --data out/pdi-train --eval out/pdi-eval --out out --epochs 60
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
from pdinet.postprocess import candidates, nms_numpy  # noqa: E402
from pdinet.coco import coco_entries, coco_map  # noqa: E402
from pdinet.loss_v5 import PARTS as V5_PARTS, yolo_v5_loss  # noqa: E402
from pdinet.loss_v8 import PARTS as V8_PARTS, yolo_v8_loss  # noqa: E402
from pdinet.model import NUM_CLASSES, PDINet  # noqa: E402

HYP = dict(rec=0.01, det=1.0, lr=0.01, momentum=0.937, wd=5e-4, lrf=0.01, clip=10.0)
# Arguments a resumed run must share with the checkpoint (the rest may change, e.g. --minutes).
FIXED = ("head", "width", "size", "batch", "seed", "epochs", "limit")


def load_split(root, size, limit=None):
    """(degraded, clean, labels) from root/degraded and root/clean, downscaled to size (W, H)."""
    names = sorted(f for f in os.listdir(os.path.join(root, "degraded")) if f.endswith(".png"))[:limit]
    raw, gt, labels = [], [], []
    for n in names:
        def img(sub):
            im = Image.open(os.path.join(root, sub, n))
            a = np.asarray(im, dtype=np.float32) / 65535.0
            if a.shape[::-1] == tuple(size):
                return a
            return np.asarray(Image.fromarray(a, mode="F").resize(size, Image.BOX), dtype=np.float32)
        raw.append(img("degraded"))
        gt.append(img("clean"))
        lp = os.path.join(root, "degraded", n[:-4] + ".txt")
        rows = np.loadtxt(lp, ndmin=2) if os.path.getsize(lp) else np.zeros((0, 5))
        labels.append(rows.astype(np.float32).reshape(-1, 5))
    return np.stack(raw)[:, None], np.stack(gt)[:, None], labels


def nms(xyxy, score, cls, head):
    """Class-aware NMS at the head's validation IoU (0.7 YOLOv8, 0.6 YOLOv5, as `pdi-compile
    verify` and evaluate.py), 300 boxes: torchvision's when installed (fast), else ours."""
    iou = 0.7 if head == "v8" else 0.6
    try:
        from torchvision.ops import batched_nms
    except ImportError:
        return nms_numpy(xyxy, score, cls, iou)
    keep = batched_nms(torch.from_numpy(xyxy), torch.from_numpy(score), torch.from_numpy(cls), iou)
    return keep[:300].numpy()


def evaluate(model, raw, labels, psf, size, head):
    """COCO mAP on the eval split: the exported decode, score > 0.001, class-aware NMS."""
    model.eval()
    w, h = size
    images, anns, dets = [], [], []
    with torch.no_grad():
        for i0 in range(0, len(raw), 16):
            x = raw[i0:i0 + 16]
            _, out = model(x, psf.expand(x.shape[0], -1, -1, -1))
            for k, o in enumerate(out.float().cpu().numpy()):
                idx = i0 + k
                images.append({"id": idx + 1, "width": w, "height": h})
                xyxy, score, cls = candidates(o, head)
                coco_entries(idx, w, h, labels[idx], xyxy, score, cls, nms(xyxy, score, cls, head), anns, dets)
    model.train()
    return coco_map(images, anns, dets)


def param_groups(model):
    """BatchNorm weights and biases without weight decay, conv weights with it (ultralytics)."""
    g_bn, g_w, g_b = [], [], []
    for mod in model.modules():
        for n, p in mod.named_parameters(recurse=False):
            if not p.requires_grad:
                continue
            (g_b if n == "bias" else g_bn if isinstance(mod, torch.nn.BatchNorm2d) else g_w).append(p)
    return [{"params": g_bn}, {"params": g_w, "weight_decay": HYP["wd"]}, {"params": g_b}]


def save_atomic(obj, path):
    tmp = path + ".tmp"
    torch.save(obj, tmp)
    os.replace(tmp, path)


def epoch_batches(n, batch, seed, epoch):
    """The epoch's batches (index arrays) and per-frame flips, fixed by (seed, epoch) alone."""
    rng = np.random.default_rng([seed, epoch])
    perm = rng.permutation(n)
    flips = rng.random(n) < 0.5
    return [(perm[i:i + batch], flips[i:i + batch]) for i in range(0, n, batch)]


def targets_for(labels, idx, flip, device):
    rows = []
    for k, (j, f) in enumerate(zip(idx, flip)):
        lab = labels[j].copy()
        if f:
            lab[:, 1] = 1 - lab[:, 1]
        rows.append(np.concatenate([np.full((len(lab), 1), k, np.float32), lab], 1))
    t = np.concatenate(rows) if rows else np.zeros((0, 6), np.float32)
    return torch.from_numpy(t).to(device)


def pick_device(name):
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--eval", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--psf", required=True, help="blur map .npy [6, 8] of the camera the frames were degraded with")
    ap.add_argument("--head", choices=["v5", "v8"], default="v5")
    ap.add_argument("--name", help="output file stem (default pdinet_{head}_w{width})")
    ap.add_argument("--size", default="256x192")
    ap.add_argument("--width", type=float, default=0.125)
    ap.add_argument("--epochs", type=int, default=40)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--limit", type=int, help="train on the first N frames only (short runs)")
    ap.add_argument("--eval-every", type=int, default=5)
    ap.add_argument("--minutes", type=float, default=1e9, help="stop after the epoch that passes this budget (checkpointed; --resume continues)")
    ap.add_argument("--device", default="auto", help="auto (CUDA when present), cpu, cuda, cuda:N")
    ap.add_argument("--threads", type=int, default=0, help="CPU threads (0 = all cores)")
    ap.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    a = ap.parse_args()
    dev = pick_device(a.device)
    torch.set_num_threads(a.threads or max(1, os.cpu_count() or 1))
    # Full-precision float on the GPU too, so CPU and GPU runs differ only by float noise.
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    torch.manual_seed(a.seed)
    size = tuple(int(v) for v in a.size.split("x"))
    stem = a.name or f"pdinet_{a.head}_w{a.width:g}"
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")

    raw, gt, labels = load_split(a.data, size, a.limit)
    eraw, _, elabels = load_split(a.eval, size)
    raw, gt, eraw = (torch.from_numpy(v).to(dev) for v in (raw, gt, eraw))
    psf = torch.from_numpy(np.load(a.psf).astype(np.float32)).view(1, 1, 6, 8).to(dev)
    model = PDINet(head=a.head, width=a.width).to(dev)
    opt = torch.optim.SGD(param_groups(model), lr=HYP["lr"], momentum=HYP["momentum"], nesterov=True)
    n = len(raw)
    nb = math.ceil(n / a.batch)
    steps, warm = a.epochs * nb, max(100, nb)
    lf = lambda s: (1 - s / steps) * (1 - HYP["lrf"]) + HYP["lrf"]  # linear decay (ultralytics lrf)
    parts_names = V5_PARTS if a.head == "v5" else V8_PARTS
    start, step, log, spent = 0, 0, [], 0.0
    if a.resume and os.path.exists(ckpt_path):
        ck = torch.load(ckpt_path, map_location=dev, weights_only=False)
        for k in FIXED:
            if ck["args"][k] != getattr(a, k):
                sys.exit(f"error: --{k} {getattr(a, k)} differs from the checkpoint's {ck['args'][k]}; start a new --out or pass the same value")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start, step, log, spent = ck["epoch"], ck["step"], ck["log"], ck["minutes"]
        print(f"resumed {ckpt_path} after epoch {start} (step {step})", flush=True)
    t0 = time.time()
    minutes = lambda: spent + (time.time() - t0) / 60
    model.train()
    for ep in range(start, a.epochs):
        tot = np.zeros(4)
        for idx, flip in epoch_batches(n, a.batch, a.seed, ep):
            x, y = raw[idx], gt[idx]
            fi = torch.from_numpy(np.where(flip)[0]).to(dev)
            if len(fi):
                x[fi], y[fi] = x[fi].flip(-1), y[fi].flip(-1)
            targets = targets_for(labels, idx, flip, dev)
            for grp in opt.param_groups:
                grp["lr"] = HYP["lr"] * lf(step) * min(1.0, (step + 1) / warm)
            recon, preds = model(x, psf.expand(len(idx), -1, -1, -1))
            l_rec = F.mse_loss(recon, y)
            if a.head == "v5":
                l_det, parts = yolo_v5_loss(preds, targets, model.detect.anchors, NUM_CLASSES)
            else:
                l_det, parts = yolo_v8_loss(preds, targets, NUM_CLASSES, model.detect.reg_max, size)
            loss = HYP["rec"] * l_rec + HYP["det"] * l_det
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), HYP["clip"])
            opt.step()
            step += 1
            tot += np.array([l_rec.item(), *parts.cpu().numpy()])
        rec = {"epoch": ep + 1, "minutes": round(minutes(), 2), "l_rec": tot[0] / nb, **{k: tot[i + 1] / nb for i, k in enumerate(parts_names)}}
        last = ep + 1 == a.epochs or minutes() > a.minutes
        if (ep + 1) % a.eval_every == 0 or last:
            rec["map50"], rec["map50_95"] = evaluate(model, eraw, elabels, psf, size, a.head)
        log.append(rec)
        print(json.dumps(rec), flush=True)
        save_atomic({"model": model.state_dict(), "optimizer": opt.state_dict(), "epoch": ep + 1, "step": step,
                     "log": log, "minutes": minutes(), "args": vars(a)}, ckpt_path)
        if last and ep + 1 < a.epochs:
            print(f"time budget of {a.minutes} min reached after epoch {ep + 1}; --resume continues", flush=True)
            break
    export(model, a, stem, eraw[:1].cpu(), psf.cpu(), size, log, n, len(eraw), minutes(), dev)


def export(model, a, stem, image, psf, size, log, n_train, n_eval, minutes, dev):
    """The ONNX file (blur map as an input, metadata as the exports carry) and training.json."""
    from pdinet.export import add_metadata

    model = model.cpu().eval()
    torch.save(model.state_dict(), os.path.join(a.out, f"{stem}.pt"))
    path = os.path.join(a.out, f"{stem}_trained.onnx")
    torch.onnx.export(model, (image, psf), path, input_names=["image", "psf_blur"], output_names=["recon", "detections"],
                      opset_version=17, do_constant_folding=True, dynamo=False)
    add_metadata(path, a.head, "input", a.width, size)
    final = log[-1] if log else {}
    info = {"log": log, "final": final, "args": vars(a), "hyp": HYP, "train_frames": n_train, "eval_frames": n_eval,
            "minutes": round(minutes, 2), "device": torch.cuda.get_device_name(dev) if dev.type == "cuda" else f"cpu x{torch.get_num_threads()}",
            "torch": torch.__version__}
    with open(os.path.join(a.out, f"{stem}_training.json"), "w") as f:
        json.dump(info, f, indent=1)
    if "map50" in final:
        print(f"final mAP@0.5 {final['map50']:.4f} mAP@0.5:0.95 {final['map50_95']:.4f} -> {path}")


if __name__ == "__main__":
    main()
