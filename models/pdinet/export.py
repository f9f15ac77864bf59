"""Export PDI-Net to ONNX the ways users do.

Variants: head {v5, v8} x blur map {input, const} x opset {13, 17} x constant folding {on, off}.
Random-weight models get realistic BatchNorm statistics: forward passes in train mode on
synthetic thermal frames before export, so activations are never degenerate.

  python -m pdinet.export --out fixtures --width 0.0625 --size 256x192
  python -m pdinet.export --out out/full --width 1.0 --size 640x480 --head v5 --psf input --opset 17

Exports as other users make them (the fixtures of models/fixtures/exports), each on top of the variants above:
  --detection-only   only the detection output (the reconstruction decoder never exported)
  --channels 3       thermal frames stored as RGB (the first convolution takes 3 channels)
  --constant-weights every initializer moved into a Constant node (Paddle / TensorFlow style)
  --plain            not PDI-Net at all: a YOLO detector on the raw frame (no reconstruction,
                     no PALS-Bridge)
"""
import argparse
import itertools
import os
import sys

import numpy as np
import torch

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from pdinet.model import PDINet, PlainDetector  # noqa: E402
from pdinet.frames import blur_map_radial, thermal_frames  # noqa: E402

CLASS_NAMES = ["People", "Car", "Bus", "Motorcycle", "Lamp", "Truck"]


def calibrate_bn(model, frames, psf, steps=6):
    """Train-mode forward passes so BN running statistics match real activations."""
    model.train()
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.momentum = None  # cumulative average over all batches
            m.reset_running_stats()
    with torch.no_grad():
        for i in range(steps):
            batch = frames[i % len(frames)]
            model(batch, psf.expand(batch.shape[0], -1, -1, -1) if model.psf_blur is None else None)
    model.eval()


class DetectionOnly(torch.nn.Module):
    """What a user exports when deployment needs no reconstruction."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, image, psf_blur=None):
        return self.model(image, psf_blur)[1]


def export_variant(out, head, psf_mode, opset, fold, width, size, seed, channels=1, detection_only=False, constant_weights=False):
    w, h = size
    torch.manual_seed(seed)
    blur = torch.from_numpy(blur_map_radial())
    model = PDINet(head=head, width=width, psf_blur=blur if psf_mode == "const" else None, in_ch=channels)
    frames = [torch.from_numpy(f).expand(-1, channels, -1, -1).contiguous() for f in thermal_frames(6, 4, h, w, seed)]
    calibrate_bn(model, frames, blur.view(1, 1, 6, 8))
    image = frames[0][:1]
    args = (image,) if psf_mode == "const" else (image, blur.view(1, 1, 6, 8))
    names = ["image"] if psf_mode == "const" else ["image", "psf_blur"]
    suffix = ("_detonly" if detection_only else "") + (f"_{channels}ch" if channels != 1 else "") + ("_constw" if constant_weights else "")
    name = f"pdinet_{head}_{psf_mode}_op{opset}_{'fold' if fold else 'nofold'}{suffix}.onnx"
    path = os.path.join(out, name)
    exported = DetectionOnly(model).eval() if detection_only else model
    torch.onnx.export(exported, args, path, input_names=names, output_names=["detections"] if detection_only else ["recon", "detections"],
                      opset_version=opset, do_constant_folding=fold, dynamo=False)
    if constant_weights:
        initializers_to_constants(path)
    add_metadata(path, head, psf_mode, width, size)
    return path


def export_plain(out, head, opset, width, size, seed):
    """A detector that is not PDI-Net: one image input, one detection output."""
    w, h = size
    torch.manual_seed(seed)
    model = PlainDetector(head=head, width=width)
    frames = [torch.from_numpy(f) for f in thermal_frames(6, 4, h, w, seed)]
    model.train()
    with torch.no_grad():
        for f in frames:
            model(f)
    model.eval()
    path = os.path.join(out, f"plain_{head}_op{opset}.onnx")
    torch.onnx.export(model, (frames[0][:1],), path, input_names=["image"], output_names=["detections"],
                      opset_version=opset, do_constant_folding=True, dynamo=False)
    return path


def initializers_to_constants(path):
    """Every initializer becomes a Constant node at the top of the graph, as Paddle's and
    tf2onnx's exporters write weights."""
    import onnx

    m = onnx.load(path)
    g = m.graph
    consts = [onnx.helper.make_node("Constant", [], [t.name], name=f"const_{i}", value=t) for i, t in enumerate(g.initializer)]
    inits = {t.name for t in g.initializer}
    kept_inputs = [v for v in g.input if v.name not in inits]
    del g.initializer[:]
    del g.input[:]
    g.input.extend(kept_inputs)
    nodes = consts + list(g.node)
    del g.node[:]
    g.node.extend(nodes)
    onnx.checker.check_model(m)
    onnx.save(m, path)


def add_metadata(path, head, psf_mode, width, size):
    """Ultralytics-style model metadata: what a deployment needs to decode the outputs."""
    import onnx

    m = onnx.load(path)
    meta = {
        "pdinet.head": head,
        "pdinet.psf_blur": psf_mode,
        "pdinet.width": str(width),
        "imgsz": f"[{size[1]}, {size[0]}]",
        "stride": "[8, 16, 32]",
        "names": str({i: n for i, n in enumerate(CLASS_NAMES)}),
    }
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    onnx.save(m, path)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--width", type=float, default=0.0625)
    ap.add_argument("--size", default="256x192", help="WxH")
    ap.add_argument("--head", choices=["v5", "v8"], action="append")
    ap.add_argument("--psf", choices=["input", "const"], action="append")
    ap.add_argument("--opset", type=int, choices=[13, 17], action="append")
    ap.add_argument("--fold", choices=["on", "off"], action="append")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--channels", type=int, default=1)
    ap.add_argument("--detection-only", action="store_true")
    ap.add_argument("--constant-weights", action="store_true")
    ap.add_argument("--plain", action="store_true")
    a = ap.parse_args()
    size = tuple(int(v) for v in a.size.split("x"))
    os.makedirs(a.out, exist_ok=True)
    if a.plain:
        for head in a.head or ["v5"]:
            p = export_plain(a.out, head, (a.opset or [17])[0], a.width, size, a.seed)
            print(f"{p}  {os.path.getsize(p) / 1e6:.2f} MB")
        return
    grid = itertools.product(a.head or ["v5", "v8"], a.psf or ["input", "const"],
                             a.opset or [13, 17], a.fold or ["on", "off"])
    for head, psf, opset, fold in grid:
        p = export_variant(a.out, head, psf, opset, fold == "on", a.width, size, a.seed,
                           a.channels, a.detection_only, a.constant_weights)
        print(f"{p}  {os.path.getsize(p) / 1e6:.2f} MB")


if __name__ == "__main__":
    main()
