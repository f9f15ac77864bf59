"""How differently a model scores inside a crop than on the whole frame: what training on crops
teaches a student that the camera's frames never ask of it.

The model is a compiled one (`pdi-compile compile MODEL --pipeline passes/detect-lossless.yaml
--psf ...`: the blur map folded into constant gate maps, one value per cell of a feature grid).
Each value named by `--value` (a head convolution's output) runs on ONNX Runtime on whole
frames and on random windows of them, the gate maps cut to each window as recovery's crops cut
them (through the trainer's own ONNX Runtime teacher, `OrtTeacher`); the sigmoids of the two are compared cell for cell inside the window, `--margin` cells in
from its edges, as a rel L2 (mean over windows).

  python src/torch/crop_context.py --model OUT/model.onnx --data EVAL/degraded \\
      --value /detect/cv3.0/cv3.0.2/Conv_output_0 --crop 256x192
"""
import argparse
import glob
import json
import os
import sys

import numpy as np
import onnx
import torch
from PIL import Image

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.join(HERE, "../../models")]
from trainer import OrtTeacher  # noqa: E402


def frame_shaped(path, frame):
    """The model's frame-shaped constants (one value per cell of a feature grid, as the crop
    plan finds them), with their stride: the gate maps a crop cuts."""
    m = onnx.load(path, load_external_data=False)
    fh, fw = frame
    kernels = {n.input[1] for n in m.graph.node if n.op_type in ("Conv", "ConvTranspose") and len(n.input) > 1}
    return {t.name: fh // t.dims[2] for t in m.graph.initializer
            if len(t.dims) == 4 and t.dims[0] == 1 and t.name not in kernels and t.dims[2] > 1 and t.dims[3] > 1
            and fh % t.dims[2] == 0 and fw % t.dims[3] == 0 and fh // t.dims[2] == fw // t.dims[3]}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", required=True)
    ap.add_argument("--data", required=True, help="a folder of 16-bit PNG frames at the model's input size")
    ap.add_argument("--value", action="append", required=True)
    ap.add_argument("--crop", default="256x192", help="WxH, multiples of 32")
    ap.add_argument("--frames", type=int, default=32)
    ap.add_argument("--windows", type=int, default=10)
    ap.add_argument("--margin", type=int, default=4, help="cells left out at each edge of a window")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args()
    files = sorted(glob.glob(os.path.join(a.data, "*.png")))[:a.frames]
    x = np.stack([np.asarray(Image.open(f), dtype=np.float32)[None] / 65535.0 for f in files])
    fh, fw = x.shape[-2:]
    cw, ch = (int(v) for v in a.crop.split("x"))
    teacher = OrtTeacher(a.model, a.value, 2, frame_shaped(a.model, (fh, fw)))
    xs = torch.from_numpy(x)

    def scores(frames):
        """The values on `frames`, 8 at a time (a whole batch at 640x480 holds gigabytes)."""
        return [torch.cat(v).numpy() for v in zip(*(teacher(frames[i:i + 8].contiguous(), a.value) for i in range(0, len(frames), 8)))]

    full = scores(xs)
    rng = np.random.default_rng(a.seed)
    sig = lambda v: 1 / (1 + np.exp(-v))  # noqa: E731
    rel = {v: [] for v in a.value}
    for _ in range(a.windows):
        y0 = int(rng.integers(0, (fh - ch) // 32 + 1)) * 32
        x0 = int(rng.integers(0, (fw - cw) // 32 + 1)) * 32
        teacher.set_window((y0, x0))
        win = scores(xs[..., y0:y0 + ch, x0:x0 + cw])
        teacher.set_window(None)
        for v, c, f in zip(a.value, win, full):
            s = fh // f.shape[-2]
            m = a.margin
            inner = c[..., m:c.shape[-2] - m, m:c.shape[-1] - m]
            same = f[..., y0 // s + m:y0 // s + c.shape[-2] - m, x0 // s + m:x0 // s + c.shape[-1] - m]
            rel[v].append(float(np.linalg.norm(sig(inner) - sig(same)) / np.linalg.norm(sig(same))))
    print(json.dumps({"model": os.path.basename(a.model), "frames": len(x), "crop": a.crop, "windows": a.windows, "margin": a.margin,
                      "rel_l2": {v: float(np.mean(r)) for v, r in rel.items()}}))


if __name__ == "__main__":
    main()
