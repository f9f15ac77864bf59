"""The interpreter checked against ONNX Runtime: every node of a model, each fed ONNX Runtime's
own values for its inputs, and the Conv forms training runs in against torch's gradients.

  python opcheck.py MODEL.onnx FRAMES.npy [DEVICE]   # one JSON line: {"event": "done", "ops": .., "gradients": ..}
"""
import json
import os
import sys

import numpy as np
import onnx
import torch
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from interpreter import Graph, attrs, conv, conv_form, fake_quant, run_node  # noqa: E402


def check(model_path, frames_path, device="cpu"):
    """Every node of the model by the interpreter against ONNX Runtime, on the frames: each
    node alone, fed ONNX Runtime's own values for its inputs (in a quantized graph a float-noise
    difference upstream flips a rounding step, which is not the op's error); the fused
    QuantizeLinear -> DequantizeLinear pairs count as DequantizeLinear, the SiLU pairs as Mul,
    and a Conv counts in each form training runs it in (`conv_form`), whose gradients are
    also compared with F.conv2d's (`conv_gradient_errors`). `device` runs the interpreter
    there (`cuda` checks the GPU's kernels; ONNX Runtime stays on the CPU)."""
    import onnxruntime as ort

    m = onnx.load(model_path)
    outs = [o for n in m.graph.node for o in n.output if o]
    exposed = onnx.ModelProto()
    exposed.CopyFrom(m)
    have = {o.name for o in exposed.graph.output}
    for o in outs:
        if o not in have:
            exposed.graph.output.append(onnx.ValueInfoProto(name=o))
    so = ort.SessionOptions()
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_DISABLE_ALL
    sess = ort.InferenceSession(exposed.SerializeToString(), so, providers=["CPUExecutionProvider"])
    dev = torch.device(device)
    g = Graph(m, trainable=False).to_device(dev)  # the layout training runs in
    x = np.load(frames_path)[:2]
    worst = {}

    def compare(op, r, v):
        r, v = r.astype(np.float64), v.detach().cpu().contiguous().numpy().astype(np.float64)
        if r.shape != v.shape:
            worst[op] = float("inf")
            return
        # Error on the value's own scale, floored at 1: a sigmoid's near-zero outputs differ
        # by ORT's approximation (~1e-6), not by a wrong op.
        worst[op] = max(worst.get(op, 0.0), float(np.abs(r - v).max() / max(np.abs(r).max(), 1.0)))

    producer = {o: n for n in m.graph.node for o in n.output}
    gradients = {}
    for i in range(len(x)):
        ref = dict(zip([o.name for o in sess.get_outputs()], sess.run(None, {g.input: x[i:i + 1]})))
        ref[g.input] = x[i:i + 1]
        value = lambda name: None if name == "" else g.consts[name] if name in g.consts else g.laid(torch.from_numpy(np.asarray(ref[name])).to(dev))
        with torch.no_grad():
            for n in m.graph.node:
                if n.op_type == "Constant" or not all(o in ref for o in n.output if o):
                    continue
                for o, v in zip(n.output, run_node(n, [value(name) for name in n.input])):
                    compare(n.op_type, ref[o], v)
                if n.op_type == "Conv":
                    # Training runs a Conv whose input needs a gradient in another form.
                    with torch.enable_grad():
                        v = run_node(n, [value(n.input[0]).detach().clone().requires_grad_(True)] + [value(name) for name in n.input[1:]])[0]
                    compare("Conv", ref[n.output[0]], v.detach())
                    for form, err in conv_gradient_errors(n, [value(name) for name in n.input]).items():
                        gradients[form] = max(gradients.get(form, 0.0), err)
                if n.op_type == "Mul" and n.output[0] in g.silu:
                    compare("Mul", ref[n.output[0]], F.silu(value(g.silu[n.output[0]][0])))
                if n.op_type == "DequantizeLinear" and n.input[0] in g.fused:
                    q = producer[n.input[0]]
                    compare(n.op_type, ref[n.output[0]], fake_quant(value(q.input[0]), *g.fused[n.input[0]]))
    print(json.dumps({"event": "done", "ops": worst, "gradients": gradients}), flush=True)


def conv_gradient_errors(n, v):
    """For each form `conv` trains node n in (input needing a gradient or not), the worst
    difference of its gradients (input, weight, bias) from F.conv2d's under a random output
    gradient, on each gradient's scale (floored at 1e-12): {form: error}."""
    a, errors = attrs(n), {}
    for needs_x in (False, True):
        x = v[0].detach().clone().requires_grad_(needs_x)
        form = conv_form(x, v[1], a)
        if form is None:
            continue
        runs = []
        for use_form in (True, False):
            xs = x.detach().clone().requires_grad_(needs_x)
            ps = [t.detach().clone().requires_grad_(True) if t is not None else None for t in v[1:3]]
            with torch.enable_grad():
                y = conv(xs, ps[0], ps[1] if len(ps) > 1 else None, a, form=use_form)
                g = torch.randn(y.shape, generator=torch.Generator().manual_seed(0)).to(y.device)
                y.backward(g.contiguous(memory_format=torch.channels_last) if y.dim() == 4 else g)
            runs.append([t.grad for t in [xs] + ps if t is not None and t.grad is not None])
        fast, plain = runs
        if len(fast) != len(plain):
            errors[form] = float("inf")
            continue
        worst = max(float((f - p).abs().max() / max(float(p.abs().max()), 1e-12)) for f, p in zip(fast, plain))
        errors[form] = max(errors.get(form, 0.0), worst)
    return errors


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        sys.exit(f"usage: {sys.argv[0]} MODEL.onnx FRAMES.npy [DEVICE]")
    check(*sys.argv[1:])
