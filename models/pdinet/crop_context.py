"""How differently a model scores inside a crop than on the whole frame: what training on crops
teaches a student that the camera's frames never ask of it.

The model is a compiled one (`pdi-compile compile MODEL --pipeline passes/detect-lossless.yaml
--psf ...`: the blur map folded into constant gate maps, one value per cell of a feature grid).
Each value named by `--value` (a head convolution's output) runs on ONNX Runtime on whole
frames and on random windows of them, the gate maps cut to each window as recovery's crops cut
them; the sigmoids of the two are compared cell for cell inside the window, `--margin` cells in
from its edges, as a rel L2 (mean over windows).

  python pdinet/crop_context.py --model OUT/model.onnx --data EVAL/degraded \\
      --value /detect/cv3.0/cv3.0.2/Conv_output_0 --crop 256x192
"""
import argparse
import glob
import json
import os

import numpy as np
import onnx
import onnxruntime as ort
from onnx import numpy_helper
from PIL import Image


def session(path, values, frame):
    """A session returning `values`, with the frame-shaped constants made inputs; and those
    constants (name -> (array, stride))."""
    m = onnx.load(path)
    fh, fw = frame
    shaped = {}
    for t in list(m.graph.initializer):
        if len(t.dims) == 4 and t.dims[2] > 1 and t.dims[3] > 1 and fh % t.dims[2] == 0 and fh // t.dims[2] == fw // t.dims[3] \
                and fw % t.dims[3] == 0 and t.dims[0] == 1:
            a = numpy_helper.to_array(t)
            # Conv kernels are not frame-shaped: their grid would be the frame's only by chance.
            if any(n.op_type in ("Conv", "ConvTranspose") and len(n.input) > 1 and n.input[1] == t.name for n in m.graph.node):
                continue
            shaped[t.name] = (a, fh // t.dims[2])
            m.graph.initializer.remove(t)
            m.graph.input.append(onnx.helper.make_tensor_value_info(t.name, onnx.TensorProto.FLOAT, None))
    # Only the cone of `values` (the decode after the heads fixes the frame's size), on
    # frames of any size.
    produced = {o: n for n in m.graph.node for o in n.output}
    need, todo = set(), list(values)
    while todo:
        n = produced.get(todo.pop())
        if n is not None and id(n) not in need:
            need.add(id(n))
            todo.extend(i for i in n.input if i)
    keep = [n for n in m.graph.node if id(n) in need]
    del m.graph.node[:]
    m.graph.node.extend(keep)
    for i in m.graph.input:
        if i.name not in shaped:
            for d in i.type.tensor_type.shape.dim[2:]:
                d.dim_param = "frame"
    del m.graph.output[:]
    m.graph.output.extend(onnx.ValueInfoProto(name=v) for v in values)
    del m.graph.value_info[:]
    so = ort.SessionOptions()
    so.log_severity_level = 3
    so.intra_op_num_threads = 2
    return ort.InferenceSession(m.SerializeToString(), so, providers=["CPUExecutionProvider"]), shaped


def run(sess, shaped, image_name, x, values, window=None):
    feeds = {image_name: x}
    for name, (a, s) in shaped.items():
        if window is None:
            feeds[name] = a
        else:
            y0, x0, h, w = window
            feeds[name] = np.ascontiguousarray(a[..., y0 // s:(y0 + h) // s, x0 // s:(x0 + w) // s])
    return sess.run(values, feeds)


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
    sess, shaped = session(a.model, a.value, (fh, fw))
    image = [i.name for i in sess.get_inputs() if i.name not in shaped][0]
    full = [np.concatenate(v) for v in zip(*(run(sess, shaped, image, x[i:i + 1], a.value) for i in range(len(x))))]
    rng = np.random.default_rng(a.seed)
    sig = lambda v: 1 / (1 + np.exp(-v))  # noqa: E731
    rel = {v: [] for v in a.value}
    for _ in range(a.windows):
        y0 = int(rng.integers(0, (fh - ch) // 32 + 1)) * 32
        x0 = int(rng.integers(0, (fw - cw) // 32 + 1)) * 32
        crop = x[..., y0:y0 + ch, x0:x0 + cw]
        win = [np.concatenate(v) for v in zip(*(run(sess, shaped, image, crop[i:i + 1], a.value, (y0, x0, ch, cw)) for i in range(len(x))))]
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
