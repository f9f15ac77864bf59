"""Learned rounding (AdaRound) for `pdi-compile`'s `quantize` pass, run in the cache's torch venv.

The float graph runs through `interpreter.py` twice, node by node over the same
frames: once in float, once with the emitted model's quantizers simulated (activations and
constant operands fake-quantized with the pass's scales and zero points, convolution weights
per-channel symmetric with the pass's scales). At each convolution to quantize, each weight's
rounding direction (down or up from its float value on the grid) is learned so that the
layer's output on the quantized model's input matches the float layer on the float input
(AdaRound, Nagel et al. 2020, with BRECQ's asymmetric target); the quantized run then goes on
with the learned integers, so later layers learn to undo what earlier ones left.

  python rounding.py CONFIG.json   # progress as JSON lines on stdout; integers to CONFIG's out folder (w{i}.npy)
"""
import json
import os
import sys
import time

import numpy as np
import onnx
import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import interpreter as rw  # noqa: E402  (checked against ONNX Runtime by opcheck.py)
from trainer import emit, setup  # noqa: E402

# The rectified sigmoid's stretch (AdaRound's zeta and gamma): h(V) reaches exactly 0 and 1
# for finite V, so the regularizer can settle every weight on a grid point.
ZETA, GAMMA = 1.1, -0.1


def fake_quant(x, p):
    """QuantizeLinear then DequantizeLinear with the pass's parameters, as ONNX Runtime does."""
    return rw.fake_quant(x, p["scale"], p["zero_point"], p["qmin"], p["qmax"])


def h_of(v):
    return torch.clamp(torch.sigmoid(v) * (ZETA - GAMMA) + GAMMA, 0, 1)


def windows(x_q, target, w, a, crop, batch, gen):
    """A function drawing `batch` random frames' `crop` x `crop` output windows: the padded
    input patch each needs and its target. The padding is applied once to the whole frame, so
    a window's output equals the full convolution's there (no border of its own)."""
    (pt, pl), (pb, pr) = rw.pads_of(a, 2)
    padded = F.pad(x_q, (pl, pr, pt, pb))
    (sh, sw), (dh, dw) = a.get("strides", [1, 1]), a.get("dilations", [1, 1])
    kh, kw = w.shape[-2:]
    oh, ow = target.shape[-2:]
    ch, cw = min(crop, oh), min(crop, ow)

    def draw():
        idx = torch.randint(len(x_q), (min(batch, len(x_q)),), generator=gen)
        oy = int(torch.randint(oh - ch + 1, (1,), generator=gen))
        ox = int(torch.randint(ow - cw + 1, (1,), generator=gen))
        patch = padded[idx, :, oy * sh:(oy + ch - 1) * sh + (kh - 1) * dh + 1, ox * sw:(ox + cw - 1) * sw + (kw - 1) * dw + 1]
        return patch, target[idx, :, oy:oy + ch, ox:ox + cw]

    return draw


def activation(post):
    """What follows the convolution, which its error is measured through: an error on a
    negative SiLU input or a far-off logit matters little; one near a score's threshold a lot."""
    kind = (post or {}).get("kind", "none")
    if kind == "silu":
        return F.silu
    if kind == "relu":
        return F.relu
    if kind == "sigmoid":
        return torch.sigmoid
    if kind == "dfl":
        r = post["reg_max"]
        return lambda x: torch.softmax(x.view(x.shape[0], -1, r, *x.shape[2:]), 2).view(x.shape)
    return lambda x: x


def learn_layer(node, w, b, scales, qmax, x_q, x_fp, cfg, gen, post=None):
    """The learned integer weights of one convolution, and how its output error moved."""
    a = rw.attrs(node)
    act = activation(post)
    unpadded = dict(a, pads=[0, 0, 0, 0])
    s = scales.view(-1, *([1] * (w.dim() - 1)))
    with torch.no_grad():
        target = torch.cat([act(rw.conv(x_fp[i:i + 4], w, b, a)) for i in range(0, len(x_fp), 4)])
    base = torch.floor(w / s)
    rest = w / s - base
    # V starts where h(V) equals the fractional part: the soft weights start at the float ones.
    v = torch.nn.Parameter(-torch.log((ZETA - GAMMA) / (rest.clamp(1e-4, 1 - 1e-4) - GAMMA) - 1))
    opt = torch.optim.Adam([v], lr=cfg["lr"])
    # Error relative to the output's mean square (one regularizer weight serves every layer);
    # for scores, relative to their variance (a mostly-zero score map has little square).
    norm = (target.var() if (post or {}).get("kind") in ("sigmoid", "dfl") else target.pow(2).mean()).clamp(min=1e-12)

    def rel_err(q_int):
        with torch.no_grad():
            wq = torch.clamp(q_int, -qmax, qmax) * s
            e = sum(float((act(rw.conv(x_q[i:i + 4], wq, b, a)) - target[i:i + 4]).pow(2).sum()) for i in range(0, len(x_q), 4))
            return e / target.numel() / float(norm)

    nearest = rel_err(torch.round(w / s))
    draw = windows(x_q, target, w, a, cfg["crop"], cfg["batch"], gen)
    iters, warm = cfg["iterations"], cfg["warmup"]
    for it in range(iters):
        patch, want = draw()
        wq = torch.clamp(base + h_of(v), -qmax, qmax) * s
        loss = (act(rw.conv(patch, wq, b, unpadded)) - want).pow(2).mean() / norm
        if it >= warm * iters:
            # beta anneals from 20 to 2: first only far-from-decided weights feel it, at the
            # end every h(V) is pushed to 0 or 1, where the hard rounding below agrees.
            t = (it - warm * iters) / max(1.0, (1 - warm) * iters)
            beta = 20 + (2 - 20) * t
            loss = loss + cfg["weight"] * (1 - (2 * h_of(v) - 1).abs().pow(beta)).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        q = torch.clamp(base + (v >= 0).float(), -qmax, qmax)
        undecided = float(((h_of(v) > 0.01) & (h_of(v) < 0.99)).float().mean())
        flipped = float((q != torch.round(w / s)).float().mean())
    return q, {"node": node.name, "rel_mse_nearest": nearest, "rel_mse_learned": rel_err(q), "flipped": flipped, "undecided": undecided}


def run(cfg):
    dev, gen = setup(cfg)
    model = onnx.load(cfg["model"])
    g = rw.Graph(model, trainable=False).to_device(dev)
    acts = cfg["activations"]
    layers = {l["node"]: l for l in cfg["layers"]}
    consts_q = dict(g.consts)
    for name, p in cfg["constants"].items():
        consts_q[name] = fake_quant(g.consts[name], p)
    frames = torch.from_numpy(np.load(cfg["frames"])).to(dev)
    # Only what the layers need (the decode after the head fixes a batch of 1), and values
    # are dropped after their last reader: two live forwards, not two whole models.
    nodes = rw.cone(g.nodes, [o for n in g.nodes if n.name in layers for o in n.output])
    last = {}
    for k, n in enumerate(nodes):
        for i in n.input:
            last[i] = k
    fp = {g.input: frames}
    q = {g.input: fake_quant(frames, acts[g.input]) if g.input in acts else frames}
    learned, report = {}, []
    start = time.time()
    emit({"event": "start", "device": str(dev), "layers": len(layers)})
    for k, n in enumerate(nodes):
        if n.op_type == "Constant":
            continue
        with torch.no_grad():
            vf = [None if i == "" else g.consts[i] if i in g.consts else fp[i] for i in n.input]
            vq = [None if i == "" else consts_q[i] if i in consts_q else q[i] for i in n.input]
            out_f = rw.run_node(n, vf)
        if n.name in layers:
            l = layers[n.name]
            scales = torch.tensor(l["scales"], dtype=torch.float32, device=dev)
            ints, r = learn_layer(n, vf[1], vf[2] if len(vf) > 2 else None, scales, l["qmax"], vq[0], vf[0], cfg, gen, l.get("post"))
            learned[n.name] = ints
            report.append(r)
            vq[1] = ints * scales.view(-1, *([1] * (ints.dim() - 1)))
            emit({"event": "layer", "done": len(report), "layers": len(layers), **r})
        with torch.no_grad():
            out_q = rw.run_node(n, vq)
        for name, a, b in zip(n.output, out_f, out_q):
            fp[name] = a
            q[name] = fake_quant(b, acts[name]) if name in acts else b
        for i in set(n.input):
            if last.get(i) == k:
                fp.pop(i, None)
                q.pop(i, None)
    seconds = time.time() - start
    for i, l in enumerate(cfg["layers"]):
        np.save(os.path.join(cfg["out"], f"w{i}.npy"), learned[l["node"]].cpu().numpy().astype(np.float32))
    emit({"event": "done", "seconds": seconds, "device": str(dev), "torch": torch.__version__, "layers": report})


if __name__ == "__main__":
    with open(sys.argv[1]) as f:
        run(json.load(f))
