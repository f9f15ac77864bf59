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

A trained model at another resolution (the network is fully convolutional; the blur map stays
6x8): the weights of a PDI-Net ONNX file (e.g. models/trained/*_trained.onnx, BatchNorm folded
into its convolutions) exported again at --size, checked against the file at its own size:
  python -m pdinet.export --out out/640 --weights-from models/trained/pdinet_v5_w0.25_trained.onnx --size 640x480
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


def module_path(node_name):
    """The torch module an exported node runs: '/neck/out5/m/m.0/cv2/conv/Conv' ->
    'neck.out5.m.0.cv2.conv' (the exporter's scopes repeat a child's parent: 'm', 'm.0')."""
    parts = []
    for seg in node_name.strip("/").split("/")[:-1]:
        if parts and seg.startswith(parts[-1] + "."):
            parts[-1] = seg
        else:
            parts.append(seg)
    return ".".join(parts)


def following_bn(modules, conv_path):
    """The BatchNorm the exporter folded into the convolution at `conv_path`."""
    parent, name = conv_path.rsplit(".", 1) if "." in conv_path else ("", conv_path)
    sibling = str(int(name) + 1) if name.isdigit() else {"conv": "bn", "pw": "bn_l"}.get(name)
    bn = modules.get(f"{parent}.{sibling}" if parent else sibling) if sibling else None
    return bn if isinstance(bn, torch.nn.BatchNorm2d) else None


def load_onnx_weights(model, path):
    """Loads the weights of a PDI-Net ONNX export of the same head and width into `model`:
    initializers named as parameters by name; a convolution whose weights the exporter renamed
    (BatchNorm folded in) through its node's name, its BatchNorm made the identity plus the
    folded bias. Fails on anything left unmatched."""
    import onnx
    from onnx import numpy_helper

    m = onnx.load(path)
    inits = {t.name: torch.from_numpy(numpy_helper.to_array(t).copy()) for t in m.graph.initializer}
    state = model.state_dict()
    modules = dict(model.named_modules())
    with torch.no_grad():
        for name, t in inits.items():
            if name in state:
                state[name].copy_(t)
        for node in m.graph.node:
            if node.op_type not in ("Conv", "ConvTranspose") or node.input[1] in state or node.input[1] not in inits:
                continue
            # The exporter's scopes can leave out a parent module (the U-Net's): match the tail.
            tail = module_path(node.name)
            found = [n for n in modules if n == tail or n.endswith("." + tail)]
            conv_path = found[0] if len(found) == 1 else tail
            conv = modules.get(conv_path)
            if not isinstance(conv, (torch.nn.Conv2d, torch.nn.ConvTranspose2d)):
                sys.exit(f"export: node {node.name} runs no convolution of this model (looked for {conv_path})")
            conv.weight.copy_(inits[node.input[1]])
            bias = inits.get(node.input[2]) if len(node.input) > 2 else None
            if conv.bias is not None:
                conv.bias.copy_(bias if bias is not None else torch.zeros_like(conv.bias))
            elif bias is not None:
                bn = following_bn(modules, conv_path)
                if bn is None:
                    sys.exit(f"export: {conv_path} has a folded bias and no BatchNorm to carry it")
                bn.weight.fill_(1.0)
                bn.bias.copy_(bias)
                bn.running_mean.zero_()
                bn.running_var.fill_(1.0 - bn.eps)
        # The gates' slopes alpha are folded into three scalars, multiplied in the order
        # PALSBridge.gates uses them.
        slopes = [inits[i] for n in m.graph.node if n.op_type == "Mul" and n.name.startswith("/bridge/")
                  for i in n.input if i in inits and i not in state and inits[i].numel() == 1]
        if len(slopes) != 3:
            sys.exit(f"export: {path}: expected the bridge's 3 gate slopes, found {len(slopes)}")
        model.bridge.alpha.copy_(torch.stack([t.reshape(()) for t in slopes]))
    return {p.key: p.value for p in m.metadata_props}


def check_against(model, path, psf_mode, frames, blur):
    """The re-exported weights give the ONNX file's detections at its own size (rel L2)."""
    import onnxruntime as ort

    sess = ort.InferenceSession(path, providers=["CPUExecutionProvider"])
    shape = sess.get_inputs()[0].shape
    image = frames(shape[3], shape[2])[:1]
    feed = {"image": image.numpy()}
    if psf_mode == "input":
        feed["psf_blur"] = blur.numpy()
    want = sess.run(["detections"], feed)[0]
    with torch.no_grad():
        got = model(image, blur if psf_mode == "input" else None)[1].numpy()
    err = float(np.linalg.norm(got - want) / max(np.linalg.norm(want), 1e-12))
    if not err < 1e-4:
        sys.exit(f"export: the weights of {path} do not reproduce its detections (rel L2 {err:.2e})")
    return err


def export_variant(out, head, psf_mode, opset, fold, width, size, seed, channels=1, detection_only=False, constant_weights=False,
                   weights_from=None):
    w, h = size
    torch.manual_seed(seed)
    blur = torch.from_numpy(blur_map_radial())
    model = PDINet(head=head, width=width, psf_blur=blur if psf_mode == "const" else None, in_ch=channels)
    frames = [torch.from_numpy(f).expand(-1, channels, -1, -1).contiguous() for f in thermal_frames(6, 4, h, w, seed)]
    if weights_from:
        load_onnx_weights(model.eval(), weights_from)
        err = check_against(model, weights_from, psf_mode,
                            lambda w_, h_: torch.from_numpy(thermal_frames(1, 1, h_, w_, seed)[0]), blur.view(1, 1, 6, 8))
        print(f"weights of {weights_from}: detections at its own size within rel L2 {err:.1e}", file=sys.stderr)
    else:
        calibrate_bn(model, frames, blur.view(1, 1, 6, 8))
    image = frames[0][:1]
    args = (image,) if psf_mode == "const" else (image, blur.view(1, 1, 6, 8))
    names = ["image"] if psf_mode == "const" else ["image", "psf_blur"]
    suffix = ("_detonly" if detection_only else "") + (f"_{channels}ch" if channels != 1 else "") + ("_constw" if constant_weights else "")
    name = f"pdinet_{head}_{psf_mode}_op{opset}_{'fold' if fold else 'nofold'}{suffix}.onnx"
    if weights_from:
        name = os.path.basename(weights_from).replace(".onnx", f"_{w}x{h}.onnx")
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
    ap.add_argument("--weights-from", metavar="ONNX", help="a trained PDI-Net ONNX file whose weights to export again")
    a = ap.parse_args()
    size = tuple(int(v) for v in a.size.split("x"))
    os.makedirs(a.out, exist_ok=True)
    if a.weights_from:
        import onnx

        meta = {p.key: p.value for p in onnx.load(a.weights_from, load_external_data=False).metadata_props}
        if "pdinet.head" not in meta or "pdinet.width" not in meta:
            sys.exit(f"export: {a.weights_from} does not say its head and width (pdinet.head, pdinet.width metadata)")
        p = export_variant(a.out, meta["pdinet.head"], "input", 17, True, float(meta["pdinet.width"]), size, a.seed,
                           weights_from=a.weights_from)
        print(f"{p}  {os.path.getsize(p) / 1e6:.2f} MB")
        return
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
