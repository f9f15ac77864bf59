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
FIXED = ("head", "width", "size", "batch", "seed", "epochs", "limit", "init", "crop", "lr")


def load_split(root, size, limit=None, raw16=False):
    """(degraded, clean, labels) from root/degraded and root/clean, downscaled to size (W, H).
    raw16: the frames as stored (16-bit, at the stored size), a quarter of the memory: for crops
    of large frames, made float a batch at a time by `as_float`."""
    names = sorted(f for f in os.listdir(os.path.join(root, "degraded")) if f.endswith(".png"))[:limit]
    raw, gt, labels = [], [], []
    for n in names:
        def img(sub):
            im = Image.open(os.path.join(root, sub, n))
            if raw16:
                a = np.asarray(im, dtype=np.uint16)
                if a.shape[::-1] != tuple(size):
                    sys.exit(f"error: --crop needs the frames at --size {size[0]}x{size[1]}; {root}/{sub}/{n} is {a.shape[1]}x{a.shape[0]}")
                return a
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


def crop_labels(lab, oy, ox, ch, cw, fh, fw):
    """A frame's YOLO labels (normalized to the frame) for its crop at (oy, ox) of size
    (ch, cw), normalized to the crop: boxes clipped to it, kept when a quarter of the box's
    area and 4 pixels of each side remain (a sliver is no object to learn)."""
    if not len(lab):
        return lab
    cx, cy, w, h = lab[:, 1] * fw, lab[:, 2] * fh, lab[:, 3] * fw, lab[:, 4] * fh
    x1, y1 = np.clip(cx - w / 2 - ox, 0, cw), np.clip(cy - h / 2 - oy, 0, ch)
    x2, y2 = np.clip(cx + w / 2 - ox, 0, cw), np.clip(cy + h / 2 - oy, 0, ch)
    keep = ((x2 - x1) >= 4) & ((y2 - y1) >= 4) & ((x2 - x1) * (y2 - y1) >= 0.25 * w * h)
    out = np.stack([lab[:, 0], (x1 + x2) / 2 / cw, (y1 + y2) / 2 / ch, (x2 - x1) / cw, (y2 - y1) / ch], 1)
    return out[keep].astype(np.float32)


def crop_offsets(n, frame, crop, rng, step=32):
    """Each frame's crop offset (y, x), on the coarsest head stride's grid, so a crop's
    features are the whole frame's features at those cells (up to the crop's borders)."""
    (fh, fw), (ch, cw) = frame, crop
    ys = rng.integers(0, (fh - ch) // step + 1, n) * step
    xs = rng.integers(0, (fw - cw) // step + 1, n) * step
    return np.stack([ys, xs], 1)


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


def epoch_batches(n, batch, seed, epoch, frame=None, crop=None):
    """The epoch's batches (index arrays), per-frame flips and crop offsets (None without
    crops), fixed by (seed, epoch) alone."""
    rng = np.random.default_rng([seed, epoch])
    perm = rng.permutation(n)
    flips = rng.random(n) < 0.5
    if crop is None:
        return [(perm[i:i + batch], flips[i:i + batch], None) for i in range(0, n, batch)]
    # Drawn after the flips, so a run without crops keeps its batches.
    offsets = crop_offsets(n, frame, crop, rng)
    return [(perm[i:i + batch], flips[i:i + batch], offsets[i:i + batch]) for i in range(0, n, batch)]


def targets_for(labels, idx, flip, device, offsets=None, frame=None, crop=None):
    rows = []
    for k, (j, f) in enumerate(zip(idx, flip)):
        lab = labels[j].copy()
        if f:
            lab[:, 1] = 1 - lab[:, 1]
        if offsets is not None:
            lab = crop_labels(lab, *offsets[k], *crop, *frame)
        rows.append(np.concatenate([np.full((len(lab), 1), k, np.float32), lab], 1))
    t = np.concatenate(rows) if rows else np.zeros((0, 6), np.float32)
    return torch.from_numpy(t).to(device)


def crops(frames, idx, flip, offsets, crop, dev):
    """The batch's crops of 16-bit frames [N, 1, H, W] (flipped first where drawn), as float."""
    ch, cw = crop
    out = np.empty((len(idx), 1, ch, cw), np.float32)
    for k, (j, f, (oy, ox)) in enumerate(zip(idx, flip, offsets)):
        im = frames[j, 0, :, ::-1] if f else frames[j, 0]
        out[k, 0] = im[oy:oy + ch, ox:ox + cw]
    return torch.from_numpy(out / np.float32(65535.0)).to(dev)


def train_mode(model, fine_tune):
    """Training mode; when fine-tuning weights whose BatchNorms were folded into the
    convolutions (`--init`), those keep their identity statistics (their scale and shift
    still learn): batch statistics would undo the fold."""
    model.train()
    if fine_tune:
        for m in model.modules():
            if isinstance(m, torch.nn.BatchNorm2d):
                m.eval()


class BusySampler:
    """On a GPU, the share of an epoch it was busy: NVML's utilization sampled every 0.1 s in
    a thread (None on the CPU or without NVML)."""

    def __init__(self, dev):
        self.samples, self.running, self.thread = [], True, None
        if dev.type != "cuda":
            return
        try:
            import pynvml
            import threading

            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(dev.index or 0)
        except Exception:
            return

        def sample():
            while self.running:
                self.samples.append(pynvml.nvmlDeviceGetUtilizationRates(handle).gpu / 100.0)
                time.sleep(0.1)

        self.thread = threading.Thread(target=sample, daemon=True)
        self.thread.start()

    def stop(self):
        self.running = False
        if self.thread is None or not self.samples:
            return None
        self.thread.join()
        return sum(self.samples) / len(self.samples)


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
    ap.add_argument("--init", metavar="ONNX", help="start from a trained PDI-Net ONNX file's weights (same head and width; any size)")
    ap.add_argument("--crop", metavar="WxH", help="train on random crops of this size of the --size frames (the blur map cut with them)")
    ap.add_argument("--lr", type=float, help=f"initial learning rate (default {HYP['lr']})")
    ap.add_argument("--amp", choices=["auto", "off", "bf16"], default="auto",
                    help="bf16 autocast of the forward (auto: on CUDA, off on the CPU; losses stay float32)")
    a = ap.parse_args()
    dev = pick_device(a.device)
    torch.set_num_threads(a.threads or max(1, os.cpu_count() or 1))
    # Full-precision float on the GPU too (unless --amp), so CPU and GPU runs differ only by
    # float noise.
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    amp = (a.amp == "bf16") or (a.amp == "auto" and dev.type == "cuda")
    if dev.type == "cuda":
        # cuDNN's fastest kernels for these shapes (a GPU run is not bit-reproducible anyway).
        torch.backends.cudnn.benchmark = True
    torch.manual_seed(a.seed)
    size = tuple(int(v) for v in a.size.split("x"))
    stem = a.name or f"pdinet_{a.head}_w{a.width:g}"
    os.makedirs(a.out, exist_ok=True)
    ckpt_path = os.path.join(a.out, "checkpoint.pt")

    crop = tuple(int(v) for v in a.crop.split("x"))[::-1] if a.crop else None  # (h, w)
    frame = size[::-1]
    if crop and (crop[0] > frame[0] or crop[1] > frame[1] or crop[0] % 32 or crop[1] % 32):
        sys.exit(f"error: --crop {a.crop} must fit in --size {a.size} and be a multiple of 32 on both sides")
    # With crops the frames stay 16-bit on the host and become float a batch at a time.
    raw, gt, labels = load_split(a.data, size, a.limit, raw16=crop is not None)
    eraw, _, elabels = load_split(a.eval, size)
    if crop is None:
        raw, gt = torch.from_numpy(raw).to(dev), torch.from_numpy(gt).to(dev)
    eraw = torch.from_numpy(eraw).to(dev)
    psf = torch.from_numpy(np.load(a.psf).astype(np.float32)).view(1, 1, 6, 8).to(dev)
    model = PDINet(head=a.head, width=a.width).to(dev)
    # On a GPU, NHWC: what its convolution kernels (and bf16's tensor cores) read without a
    # transpose around each layer.
    layout = torch.channels_last if dev.type == "cuda" else torch.contiguous_format
    if a.init:
        from pdinet.export import load_onnx_weights

        load_onnx_weights(model, a.init)
    lr0 = a.lr if a.lr is not None else HYP["lr"]
    opt = torch.optim.SGD(param_groups(model), lr=lr0, momentum=HYP["momentum"], nesterov=True)
    n = len(raw)
    nb = math.ceil(n / a.batch)
    steps, warm = a.epochs * nb, max(100, nb)
    lf = lambda s: (1 - s / steps) * (1 - HYP["lrf"]) + HYP["lrf"]  # linear decay (ultralytics lrf)
    parts_names = V5_PARTS if a.head == "v5" else V8_PARTS
    start, step, log, spent = 0, 0, [], 0.0
    if a.resume and os.path.exists(ckpt_path):
        ck = torch.load(ckpt_path, map_location=dev, weights_only=False)
        for k in FIXED:
            if ck["args"].get(k) != getattr(a, k):
                sys.exit(f"error: --{k} {getattr(a, k)} differs from the checkpoint's {ck['args'].get(k)}; start a new --out or pass the same value")
        model.load_state_dict(ck["model"])
        opt.load_state_dict(ck["optimizer"])
        start, step, log, spent = ck["epoch"], ck["step"], ck["log"], ck["minutes"]
        print(f"resumed {ckpt_path} after epoch {start} (step {step})", flush=True)
    model = model.to(memory_format=layout)
    t0 = time.time()
    minutes = lambda: spent + (time.time() - t0) / 60
    train_mode(model, a.init)
    for ep in range(start, a.epochs):
        tot = np.zeros(4) if dev.type == "cpu" else torch.zeros(4, device=dev)
        epoch_start, busy = time.time(), BusySampler(dev)
        for idx, flip, offsets in epoch_batches(n, a.batch, a.seed, ep, frame, crop):
            if crop is None:
                x, y = raw[idx], gt[idx]
                fi = torch.from_numpy(np.where(flip)[0]).to(dev)
                if len(fi):
                    x[fi], y[fi] = x[fi].flip(-1), y[fi].flip(-1)
                window = None
            else:
                x, y = crops(raw, idx, flip, offsets, crop, dev), crops(gt, idx, flip, offsets, crop, dev)
                window = (frame, crop, [tuple(int(v) for v in o) for o in offsets])
            targets = targets_for(labels, idx, flip, dev, offsets, frame, crop)
            for grp in opt.param_groups:
                grp["lr"] = lr0 * lf(step) * min(1.0, (step + 1) / warm)
            x = x.contiguous(memory_format=layout)
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp):
                recon, preds = model(x, psf.expand(len(idx), -1, -1, -1), window)
            # The losses in float32: bf16's 8 bits of mantissa would round the box terms.
            recon, preds = recon.float(), [p.float() for p in preds] if isinstance(preds, (list, tuple)) else preds.float()
            l_rec = F.mse_loss(recon, y)
            if a.head == "v5":
                l_det, parts = yolo_v5_loss(preds, targets, model.detect.anchors, NUM_CLASSES)
            else:
                l_det, parts = yolo_v8_loss(preds, targets, NUM_CLASSES, model.detect.reg_max, crop[::-1] if crop else size)
            loss = HYP["rec"] * l_rec + HYP["det"] * l_det
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), HYP["clip"])
            opt.step()
            step += 1
            if dev.type == "cpu":
                tot += np.array([l_rec.item(), *parts.cpu().numpy()])
            else:  # summed where it lives: a read each step would wait for the GPU
                tot += torch.cat([l_rec.detach().view(1), parts.detach().view(-1)])
        tot = tot if dev.type == "cpu" else tot.cpu().numpy()
        seconds = time.time() - epoch_start
        rec = {"epoch": ep + 1, "minutes": round(minutes(), 2), "l_rec": tot[0] / nb, **{k: tot[i + 1] / nb for i, k in enumerate(parts_names)},
               "frames_per_second": round(n / max(seconds, 1e-9), 1)}
        share = busy.stop()
        if share is not None:
            rec["gpu_busy_share"] = round(share, 3)
        last = ep + 1 == a.epochs or minutes() > a.minutes
        if (ep + 1) % a.eval_every == 0 or last:
            rec["map50"], rec["map50_95"] = evaluate(model, eraw, elabels, psf, size, a.head)
            train_mode(model, a.init)
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
