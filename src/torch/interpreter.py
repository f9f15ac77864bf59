"""The ONNX graphs `pdi-compile` emits, run as torch modules: a small interpreter of their ops
(each checked against ONNX Runtime by `opcheck.py`). A pruned student's Conv weights and biases
are parameters; everything else (PSF gate maps, upsampling kernels, decode constants) stays
fixed. A quantized (QDQ) student runs the same way: its QuantizeLinear / DequantizeLinear
nodes are fake quantization with straight-through rounding, its integer weights and biases the
parameters (see `Graph`). Imported by `trainer.py`, `opcheck.py` and `rounding.py`.
"""
import math

import numpy as np
import onnx
import torch
import torch.nn.functional as F
from onnx import numpy_helper


def attrs(node):
    return {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}


def pads_of(a, k):
    p = list(a.get("pads", [0] * (2 * k)))
    return p[:k], p[k:]


# A convolution of an input with at most this many channels that needs no gradient (the
# image) runs as columns (below): oneDNN vectorizes over input channels, and with one it
# falls back to a kernel that took 46 ms forward and backward for the width-0.25 v5's stem
# (batch 16, 256x192, 2 cores), against 8 ms as nine shifted views and a 1x1 convolution.
# Inside the network the views' gradients cost more than they save (measured: 2x slower).
FEW_CHANNELS = 4

# A depthwise kernel at least this large (7x7) computes its weight gradient as a depthwise
# convolution of the frames by the output gradients (below): oneDNN's own took 29 ms for
# the 15x15 PSF kernel of the same model, against 3 ms.
LARGE_KERNEL = 49


def conv_form(x, w, a):
    """How `conv` runs: "columns", "depthwise" (its own weight gradient) or None (F.conv2d).
    Only on the CPU: the two forms work around oneDNN's slow kernels (measured there)."""
    stride, dilation, groups = a.get("strides", [1, 1]), a.get("dilations", [1, 1]), a.get("group", 1)
    if dilation != [1, 1] or x.device.type != "cpu":
        return None
    if groups == 1 and x.shape[1] <= FEW_CHANNELS and not x.requires_grad and w.shape[2] * w.shape[3] > 1:
        return "columns"
    if stride == [1, 1] and groups == x.shape[1] == w.shape[0] > 1 and w.shape[1] == 1 and w.shape[2] * w.shape[3] >= LARGE_KERNEL:
        return "depthwise"
    return None


def conv(x, w, b, a, form=True):
    """An ONNX Conv; `form=False` always runs plain F.conv2d (what `check` compares with)."""
    begin, end = pads_of(a, 2)
    if begin != end:
        x = F.pad(x, (begin[1], end[1], begin[0], end[0]))
        begin = [0, 0]
    stride, dilation, groups = a.get("strides", [1, 1]), a.get("dilations", [1, 1]), a.get("group", 1)
    kind = conv_form(x, w, a) if form else None
    if kind == "columns":
        return conv_by_columns(x, w, b, stride, begin)
    if kind == "depthwise":
        return DepthwiseConv.apply(x, w, b, begin)
    return F.conv2d(x, w, b, stride, begin, dilation, groups)


def conv_by_columns(x, w, b, stride, pads):
    """A convolution of a few-channel input as one 1x1 convolution over its kernel's shifted
    views (im2col in channel-major, then row, then column order: the weight's own)."""
    (kh, kw), (sh, sw) = w.shape[2:], stride
    x = F.pad(x, (pads[1], pads[1], pads[0], pads[0]))
    ho, wo = (x.shape[2] - kh) // sh + 1, (x.shape[3] - kw) // sw + 1
    views = [x[:, c, i:i + sh * (ho - 1) + 1:sh, j:j + sw * (wo - 1) + 1:sw] for c in range(x.shape[1]) for i in range(kh) for j in range(kw)]
    cols = torch.stack(views, -1).permute(0, 3, 1, 2)  # channels-last, written once
    return F.conv2d(cols, w.reshape(w.shape[0], -1, 1, 1), b)


class DepthwiseConv(torch.autograd.Function):
    """A stride-1 depthwise convolution; its weight gradient, a correlation of each channel's
    input with its output gradient summed over the batch, runs as one depthwise convolution
    with the batch folded into the channels (the gradient becomes the kernel)."""

    @staticmethod
    def forward(ctx, x, w, b, pads):
        ctx.save_for_backward(x, w)
        ctx.pads, ctx.has_bias = pads, b is not None
        return F.conv2d(x, w, b, 1, pads, 1, x.shape[1])

    @staticmethod
    def backward(ctx, g):
        x, w = ctx.saved_tensors
        (ph, pw), (n, c, h, wd), (kh, kw) = ctx.pads, x.shape, w.shape[2:]
        gx = gw = gb = None
        if ctx.needs_input_grad[0]:
            gx = torch.ops.aten.convolution_backward(g, x, w, None, [1, 1], [ph, pw], [1, 1], False, [0, 0], c, [True, False, False])[0]
        if ctx.needs_input_grad[1]:
            xs = F.pad(x, (pw, pw, ph, ph)).transpose(0, 1).reshape(1, c * n, h + 2 * ph, wd + 2 * pw)
            gs = g.transpose(0, 1).reshape(c * n, 1, *g.shape[2:])
            gw = F.conv2d(xs, gs, None, 1, 0, 1, c * n).view(c, n, kh, kw).sum(1, keepdim=True)
            gw = gw.contiguous(memory_format=torch.channels_last if w.is_contiguous(memory_format=torch.channels_last) else torch.contiguous_format)
        if ctx.has_bias and ctx.needs_input_grad[2]:
            gb = g.sum((0, 2, 3))
        return gx, gw, gb, None


def conv_transpose(x, w, b, a):
    begin, end = pads_of(a, 2)
    if begin != end:
        raise ValueError("ConvTranspose with asymmetric pads is not interpreted")
    return F.conv_transpose2d(x, w, b, a.get("strides", [1, 1]), begin, a.get("output_padding", [0, 0]), a.get("group", 1), a.get("dilations", [1, 1]))


def max_pool(x, a):
    begin, end = pads_of(a, 2)
    if begin != end:
        x = F.pad(x, (begin[1], end[1], begin[0], end[0]), value=float("-inf"))
        begin = [0, 0]
    return F.max_pool2d(x, a["kernel_shape"], a.get("strides", [1, 1]), begin, a.get("dilations", [1, 1]), ceil_mode=bool(a.get("ceil_mode", 0)))


def split(x, sizes, a, n_out):
    axis = a.get("axis", 0)
    if sizes is None:
        sizes = a.get("split")
    if sizes is None:
        sizes = [x.shape[axis] // n_out] * n_out
    return list(torch.split(x, [int(s) for s in sizes], axis))


def slice_(x, starts, ends, axes, steps):
    axes = range(len(starts)) if axes is None else axes
    steps = [1] * len(starts) if steps is None else steps
    idx = [slice(None)] * x.dim()
    for s, e, ax, st in zip(starts, ends, axes, steps):
        ax, n = int(ax) % x.dim(), x.shape[int(ax)]
        s, e = int(max(min(s, n), -n)), int(max(min(e, n), -n - 1))
        idx[ax] = slice(s, e, int(st))
    return x[tuple(idx)]


def reshape(x, shape):
    shape = [int(v) for v in shape]
    shape = [x.shape[i] if v == 0 else v for i, v in enumerate(shape)]
    return x.reshape(shape)


def ints(t):
    """An operand's integers: a tensor's, or a list `Graph.plan` read from a constant once."""
    if t is None or isinstance(t, list):
        return t
    return [int(v) for v in t.flatten().tolist()]


def ste_round(x):
    """Rounding half to even (as ONNX Runtime's QuantizeLinear) whose gradient passes
    straight through: what quantization-aware training differentiates."""
    return x + (torch.round(x) - x).detach()


def integer_bounds(dtype):
    return {torch.uint8: (0, 255), torch.int8: (-128, 127), torch.int32: (-(2 ** 31), 2 ** 31 - 1)}[dtype]


def along(p, x, axis):
    """A scale or zero point broadcast against x: per tensor, or per channel along `axis`."""
    if p.dim() == 0 or p.numel() == 1:
        return p.reshape(())
    shape = [1] * x.dim()
    shape[axis % x.dim()] = -1
    return p.reshape(shape)


def quantize_linear(x, scale, zp, a):
    """The integers ONNX Runtime would store, as floats (so gradients pass); outside the
    integer range the clamp stops them, as a saturated value does not move."""
    axis = a.get("axis", 1)
    lo, hi = integer_bounds(zp.dtype) if zp is not None else (0, 255)
    z = 0.0 if zp is None else along(zp.float(), x, axis)
    return torch.clamp(ste_round(x / along(scale, x, axis)) + z, lo, hi)


def dequantize_linear(q, scale, zp, a):
    axis = a.get("axis", 1)
    z = 0.0 if zp is None else along(zp.float(), q, axis)
    return (q.float() - z) * along(scale, q, axis)


def run_node(n, v, a=None):
    """Outputs of node n given its input values v (None for omitted optional inputs) and its
    attributes `a` (parsed from n when not given)."""
    a, op = attrs(n) if a is None else a, n.op_type
    if op == "QuantizeLinear":
        return [quantize_linear(v[0], v[1], v[2] if len(v) > 2 else None, a)]
    if op == "DequantizeLinear":
        return [dequantize_linear(v[0], v[1], v[2] if len(v) > 2 else None, a)]
    if op == "Conv":
        return [conv(v[0], v[1], v[2] if len(v) > 2 else None, a)]
    if op == "ConvTranspose":
        return [conv_transpose(v[0], v[1], v[2] if len(v) > 2 else None, a)]
    binary = {"Add": torch.add, "Sub": torch.sub, "Mul": torch.mul, "Div": torch.div, "Pow": torch.pow}
    if op in binary:
        return [binary[op](v[0], v[1])]
    unary = {"Relu": F.relu, "Sigmoid": torch.sigmoid, "Identity": lambda x: x, "Exp": torch.exp, "Tanh": torch.tanh, "Neg": torch.neg, "Sqrt": torch.sqrt}
    if op in unary:
        return [unary[op](v[0])]
    if op == "Clip":
        lo = v[1] if len(v) > 1 and v[1] is not None else a.get("min")
        hi = v[2] if len(v) > 2 and v[2] is not None else a.get("max")
        return [torch.clamp(v[0], None if lo is None else float(lo), None if hi is None else float(hi))]
    if op == "Concat":
        # A constant of the graph's batch of 1 (a halo's mean rows) joins the worker's batch.
        b = max(t.shape[0] for t in v)
        if a["axis"] % v[0].dim() != 0:
            v = [t.expand(b, *t.shape[1:]) if t.shape[0] == 1 else t for t in v]
        return [torch.cat(v, a["axis"])]
    if op == "Split":
        return split(v[0], ints(v[1]) if len(v) > 1 and v[1] is not None else None, a, len(n.output))
    if op == "Slice":
        return [slice_(v[0], ints(v[1]), ints(v[2]), ints(v[3]) if len(v) > 3 else None, ints(v[4]) if len(v) > 4 else None)]
    if op == "MaxPool":
        return [max_pool(v[0], a)]
    if op == "GlobalAveragePool":
        return [v[0].mean(dim=tuple(range(2, v[0].dim())), keepdim=True)]
    if op == "ReduceMean":
        axes = ints(v[1]) if len(v) > 1 and v[1] is not None else a.get("axes")
        return [v[0].mean(dim=tuple(axes), keepdim=bool(a.get("keepdims", 1)))]
    if op == "ReduceSum":
        # Axes are an input from opset 13 (an attribute before); none given: every axis.
        axes = ints(v[1]) if len(v) > 1 and v[1] is not None else a.get("axes")
        if not axes:
            return [v[0].clone() if a.get("noop_with_empty_axes", 0) else v[0].sum().reshape([1] * v[0].dim() if a.get("keepdims", 1) else [])]
        return [v[0].sum(dim=tuple(axes), keepdim=bool(a.get("keepdims", 1)))]
    if op == "Reshape":
        return [reshape(v[0], ints(v[1]))]
    if op == "Transpose":
        return [v[0].permute(*a["perm"])]
    if op == "Softmax":
        return [torch.softmax(v[0], a.get("axis", -1))]
    if op == "Resize":
        scales = v[2] if len(v) > 2 and v[2] is not None and len(v[2]) else None
        if a.get("mode", b"nearest") not in (b"nearest", "nearest") or scales is None:
            raise ValueError("only nearest Resize by scales is interpreted")
        return [F.interpolate(v[0], scale_factor=[float(s) for s in scales[2:]], mode="nearest")]
    raise ValueError(f"op {op} ('{n.name}') is not interpreted; recovery cannot train this model")


def cone(nodes, wanted):
    """The nodes (in order) that the values `wanted` need."""
    need, keep = set(wanted), []
    for n in reversed(nodes):
        if any(o in need for o in n.output):
            keep.append(n)
            need.update(i for i in n.input if i)
    return keep[::-1]


def fake_quant(x, scale, zp, lo, hi):
    """QuantizeLinear then DequantizeLinear in three passes. torch's fused kernel multiplies
    by 1/scale, which rounds a few values the other way from ONNX Runtime's x / scale; so the
    division comes first and the kernel runs at scale 1 (its clamp and gradient mask are
    unchanged by it)."""
    return torch.fake_quantize_per_tensor_affine(x / scale, 1.0, zp, lo, hi) * scale


def readers_of(g):
    """Value name -> the nodes that read it."""
    readers = {}
    for n in g.node:
        for i in n.input:
            readers.setdefault(i, []).append(n)
    return readers


def fused_pairs(g):
    """QuantizeLinear outputs read only by DequantizeLinear nodes with the same per-tensor
    scale and zero point, with (scale, zero point, qmin, qmax): such a pair runs as one fake
    quantization, three elementwise passes over the activation instead of eight (the same
    round-half-to-even, clamp and straight-through gradient; `check` compares both
    forms with ONNX Runtime)."""
    consts = {t.name: numpy_helper.to_array(t) for t in g.initializer}
    readers, outputs = readers_of(g), {o.name for o in g.output}
    fused = {}
    for n in g.node:
        if n.op_type != "QuantizeLinear" or len(n.input) < 3 or n.output[0] in outputs:
            continue
        scale, zp = consts.get(n.input[1]), consts.get(n.input[2])
        rs = readers.get(n.output[0], [])
        if scale is None or zp is None or scale.size != 1 or zp.dtype not in (np.uint8, np.int8) or not rs:
            continue
        if all(r.op_type == "DequantizeLinear" and list(r.input[1:]) == list(n.input[1:]) for r in rs):
            fused[n.output[0]] = (float(scale.reshape(())), int(zp.reshape(())), *integer_bounds(torch.from_numpy(zp).dtype))
    return fused


def silu_pairs(g):
    """Mul outputs that are x * Sigmoid(x), the Sigmoid read by nothing else, with the names of
    x and of the Sigmoid's output: each runs as torch's SiLU, one pass forward and one
    backward instead of three (the same function; `check` compares it with ONNX Runtime's
    Mul)."""
    readers, outputs = readers_of(g), {o.name for o in g.output}
    pairs = {}
    for n in g.node:
        if n.op_type != "Sigmoid" or n.output[0] in outputs:
            continue
        rs = readers.get(n.output[0], [])
        if len(rs) == 1 and rs[0].op_type == "Mul" and sorted(rs[0].input) == sorted([n.input[0], n.output[0]]):
            pairs[rs[0].output[0]] = (n.input[0], n.output[0])
    return pairs


# The operands (by position) read as host numbers when constant: what `run_node` turns into
# Python numbers anyway (a read from the device on CUDA, at every step without `Graph.plan`).
HOST_OPERANDS = {
    "Slice": {1: "ints", 2: "ints", 3: "ints", 4: "ints"},
    "Reshape": {1: "ints"},
    "Split": {1: "ints"},
    "ReduceMean": {1: "ints"},
    "ReduceSum": {1: "ints"},
    "Resize": {2: "floats"},
    "Clip": {1: "float", 2: "float"},
}


# The largest int32 a float32 holds exactly (its spacing is 128 just below 2^31): int32
# biases trained as float32 stay in range when written back.
INT32_IN_F32 = 2 ** 31 - 128


class Graph(torch.nn.Module):
    """An ONNX graph as a torch module: Conv weights and biases become parameters.

    In a quantized (QDQ) graph they are integers behind DequantizeLinear: each becomes a
    float parameter in integer units, rounded (straight through) and clamped to `weight_qmax`
    (int8 weights) or int32's range (biases) wherever it is read, so the forward is the
    emitted model's and the parameter keeps what a step moved below one integer.
    With `only` (a set of initializer names), exactly those float initializers train, whatever
    reads them: a crop's halo and pool-correction constants, the network's weights fixed.
    With `scale_groups` (lists of activation scale initializers that must stay equal), each
    group's scale trains too (LSQ: the fake quantizer's own gradient with respect to its
    step), and the int32 biases read with it are requantized to it (`requantize_bias`)."""

    def __init__(self, model, trainable=True, weight_qmax=127, fuse=True, pin_extremes=False, weight_qmin=None, only=None, scale_groups=()):
        super().__init__()
        g = model.graph
        self.nodes = list(g.node)
        self.fused = fused_pairs(g) if fuse else {}
        # The fused pairs' scale initializers, so that a learned scale reaches them.
        self.fused_scale = {n.output[0]: n.input[1] for n in self.nodes if n.op_type == "QuantizeLinear" and n.output[0] in self.fused}
        group_of = {name: k for k, names in enumerate(scale_groups) for name in names} if trainable else {}
        self.scales = set()  # parameter keys of learned scales
        group_key = {}  # scale group -> its parameter key
        self.silu = silu_pairs(g) if fuse else {}
        self.silu_gates = {gate for _, gate in self.silu.values()}
        self.input = [i.name for i in g.input if i.name not in {t.name for t in g.initializer}][0]
        conv_params = {i for n in self.nodes if n.op_type == "Conv" for i in n.input[1:]}
        integer_params = {n.input[0] for n in self.nodes if n.op_type == "DequantizeLinear" and n.output[0] in conv_params}
        self.params = torch.nn.ParameterDict()
        self.key = {}
        self.consts = {}
        self.bounds = {}  # parameter key -> (lo, hi) of an integer initializer
        self.pinned = {}  # parameter key -> mask of integers that must not move
        for t in g.initializer:
            arr = numpy_helper.to_array(t)
            if t.name in group_of:
                # One parameter per group, from the group's first initializer met.
                if group_of[t.name] not in group_key:
                    k = group_key[group_of[t.name]] = f"p{len(self.params)}"
                    self.params[k] = torch.nn.Parameter(torch.tensor(float(arr.reshape(())), dtype=torch.float32))
                    self.scales.add(k)
                self.key[t.name] = group_key[group_of[t.name]]
            elif only is not None:
                # Exactly the named float initializers train, whichever op reads them.
                if trainable and t.name in only and arr.dtype == np.float32:
                    k = f"p{len(self.params)}"
                    self.params[k] = torch.nn.Parameter(torch.from_numpy(arr.copy()))
                    self.key[t.name] = k
                else:
                    self.consts[t.name] = torch.from_numpy(arr.copy())
            elif trainable and t.name in conv_params and arr.dtype == np.float32:
                k = f"p{len(self.params)}"
                self.params[k] = torch.nn.Parameter(torch.from_numpy(arr.copy()))
                self.key[t.name] = k
            elif trainable and t.name in integer_params and arr.dtype in (np.int8, np.int32):
                k = f"p{len(self.params)}"
                self.params[k] = torch.nn.Parameter(torch.from_numpy(arr.astype(np.float32)))
                self.key[t.name] = k
                lo = -weight_qmax if weight_qmin is None else weight_qmin
                self.bounds[k] = (lo, weight_qmax) if arr.dtype == np.int8 else (-INT32_IN_F32, INT32_IN_F32)
                if pin_extremes and arr.dtype == np.int8:
                    # Weights at the range's ends stay there: a toolchain that requantizes the
                    # dequantized weights per channel over their min..max then finds the same grid.
                    self.pinned[k] = (torch.from_numpy((arr == lo) | (arr == weight_qmax)), self.params[k].detach().clone())
            else:
                self.consts[t.name] = torch.from_numpy(arr.copy())
        for n in self.nodes:
            if n.op_type == "Constant":
                self.consts[n.output[0]] = torch.from_numpy(numpy_helper.to_array(n.attribute[0].t).copy())
        self.requant = self.requantized_bias_inputs() if self.scales else {}
        # Frame-shaped constants cut to crops (`crop_constants`): name -> stride, whole value, buffer.
        self.crop_strides, self.crop_full, self.crop_buf = {}, {}, {}
        self.plans = {}  # wanted values -> the nodes they need, computed once per request
        self.layout = torch.contiguous_format

    def to_device(self, dev):
        """Moves the graph to `dev`. On the CPU images and convolution weights go channels-last
        (NHWC): oneDNN's convolutions, forward and backward, then skip the layout reorders
        they pay on NCHW. Measured on the pruned width-0.25 v5, batch 16, 2 cores: a training
        step 0.17-0.20 s against 0.32 s on the same AVX-512 machine. Same products, summed in
        another order (the op check runs this layout)."""
        if dev.type == "cpu":
            self.layout = torch.channels_last
        self.consts = {k: self.laid(v.to(dev)) for k, v in self.consts.items()}
        self.pinned = {k: (self.laid(m.to(dev)), self.laid(v.to(dev))) for k, (m, v) in self.pinned.items()}
        self.to(dev)
        with torch.no_grad():
            for p in self.params.values():
                p.data = self.laid(p.data)
        return self

    def crop_constants(self, strides, size):
        """Prepares training on crops of `size` (h, w): the frame-shaped constants named in
        `strides` (name -> the stride of their feature grid) get a buffer of the crop's cells,
        which `set_window` fills; the buffers stay where they are, so a captured CUDA graph
        reads each step's window."""
        h, w = size
        self.crop_strides, self.crop_full, self.crop_buf = dict(strides), {}, {}
        for name, s in strides.items():
            if name in self.key:
                raise ValueError(f"constant {name} trains and cannot be cut to a crop")
            full = self.consts[name]
            self.crop_full[name] = full
            self.crop_buf[name] = self.laid(full.new_empty(*full.shape[:-2], h // s, w // s))

    def set_window(self, offset):
        """The frame-shaped constants cut to the crop at `offset` (y, x) in pixels, or whole
        (None)."""
        if not self.crop_buf:
            return
        if offset is None:
            self.consts.update(self.crop_full)
            return
        y, x = offset
        with torch.no_grad():
            for name, buf in self.crop_buf.items():
                s = self.crop_strides[name]
                buf.copy_(self.crop_full[name][..., y // s:y // s + buf.shape[-2], x // s:x // s + buf.shape[-1]])
                self.consts[name] = buf

    def laid(self, x):
        """A 4-D tensor in the graph's memory layout (values are unchanged)."""
        return x.contiguous(memory_format=self.layout) if x.dim() == 4 else x

    def restore_pinned(self):
        """Puts pinned integers back where they started (after an optimizer step)."""
        with torch.no_grad():
            for k, (mask, start) in self.pinned.items():
                self.params[k].copy_(torch.where(mask, start, self.params[k]))

    def value(self, name, env):
        if name == "":
            return None
        if name in self.key:
            k = self.key[name]
            if k in self.bounds:
                return ste_round(self.params[k].clamp(*self.bounds[k]))
            if k in self.scales:
                return self.params[k].clamp(min=1e-12)
            return self.params[k]
        if name in self.consts:
            return self.consts[name]
        return env[name]

    def forward(self, x, wanted):
        """The values named in `wanted`, computing only what they need."""
        env = {self.input: self.laid(x)}
        key = tuple(wanted)
        if key not in self.plans:
            self.plans[key] = self.plan(key)
        for step in self.plans[key]:
            step(env)
        return [env[w] for w in wanted]

    def plan(self, wanted):
        """The steps that compute `wanted`, built once per request: each node's attributes are
        parsed and its constant shape, bound and scale operands read to the host here, so a
        forward is a walk over prepared closures with no protobuf parsing and no read from
        the device (which CUDA graph capture forbids). The same ops in the same order as the
        node list: the values are the node-by-node interpreter's, to the bit."""
        steps = []
        for n in cone(self.nodes, list(wanted)):
            out = n.output[0]
            if n.op_type == "Constant":
                continue
            if n.op_type == "QuantizeLinear" and out in self.fused:
                scale, zp, lo, hi = self.fused[out]
                learned = self.fused_scale[out] if self.fused_scale[out] in self.key else None
                steps.append(lambda env, i=n.input[0], o=out, s=scale, zp=zp, lo=lo, hi=hi, learned=learned:
                             env.__setitem__(o, fake_quant(env[i], s if learned is None else self.value(learned, env), zp, lo, hi)))
                continue
            if n.op_type == "DequantizeLinear" and n.input[0] in self.fused:
                steps.append(lambda env, i=n.input[0], o=out: env.__setitem__(o, env[i]))
                continue
            if n.op_type == "Sigmoid" and out in self.silu_gates and out not in wanted:
                continue
            if n.op_type == "Mul" and out in self.silu:
                steps.append(lambda env, i=self.silu[out][0], o=out: env.__setitem__(o, F.silu(env[i])))
                continue
            steps.append(self.node_step(n))
        return steps

    def node_step(self, n):
        """One node as a closure over its parsed attributes and its operands' getters."""
        a = attrs(n)
        getters = [self.getter(n, k, name) for k, name in enumerate(n.input)]
        requant = [o in self.requant for o in n.output]

        def step(env):
            for o, val, rq in zip(n.output, run_node(n, [g(env) for g in getters], a), requant):
                env[o] = self.requantize_bias(o, val) if rq else val
        return step

    def getter(self, n, k, name):
        """How the node reads operand k: a constant shape, bound or scale as host numbers
        (`HOST_OPERANDS`), anything else through `value` at run time."""
        kind = HOST_OPERANDS.get(n.op_type, {}).get(k)
        if kind is not None and name in self.consts and name not in self.key:
            t = self.consts[name]
            host = ints(t) if kind == "ints" else ([float(v) for v in t.flatten().tolist()] if kind == "floats" else float(t))
            return lambda env: host
        return lambda env: self.value(name, env)

    def write_back(self, model):
        """The trained parameters into `model`'s initializers (same names, shapes, order)."""
        rescaled = self.requantized_biases() if self.scales else {}
        for t in model.graph.initializer:
            if t.name in rescaled:
                t.CopyFrom(numpy_helper.from_array(rescaled[t.name], t.name))
            elif t.name in self.key:
                k = self.key[t.name]
                p = self.params[k].detach()
                if k in self.scales:
                    arr = p.reshape(numpy_helper.to_array(t).shape).cpu().numpy().astype(np.float32)
                elif k in self.bounds:
                    arr = torch.round(p.clamp(*self.bounds[k])).contiguous().cpu().numpy().astype(numpy_helper.to_array(t).dtype)
                else:
                    arr = p.contiguous().cpu().numpy().astype(np.float32)
                t.CopyFrom(numpy_helper.from_array(arr, t.name))

    def requantized_bias_inputs(self):
        """Int32 bias DequantizeLinear outputs whose convolution's input scale is learned, with
        that input scale's and the weight scale's names and the DequantizeLinear node. An int32 bias's scale must be its
        input's scale times the weight's (ONNX Runtime's integer convolution assumes it), so
        such a bias is requantized to the product in every forward (`requantize_bias`), as
        it will be written: the first layer's bias step (the frame's scale times a large
        weight scale) is coarse enough that requantizing only when writing moved the outputs."""
        dq = {n.output[0]: n for n in self.nodes if n.op_type == "DequantizeLinear"}
        out = {}
        for n in self.nodes:
            if n.op_type not in ("Conv", "ConvTranspose") or len(n.input) < 3 or not all(i in dq for i in n.input[:3]):
                continue
            x, w, b = (dq[i] for i in n.input[:3])
            ints = self.consts.get(b.input[0]) if b.input[0] not in self.key else self.params[self.key[b.input[0]]]
            if self.key.get(x.input[1]) in self.scales and ints is not None and (b.input[0] in self.key or ints.dtype == torch.int32):
                out[b.output[0]] = (x.input[1], w.input[1], b)
        return out

    def bias_step(self, name):
        """The grid of requantized bias `name`: its input's current scale times the weight's."""
        x_scale, w_scale, _ = self.requant[name]
        return self.value(x_scale, {}) * self.value(w_scale, {})

    def requantize_bias(self, name, value):
        """A bias (float, from its old integers) on the grid of its input's current scale."""
        step = self.bias_step(name)
        return ste_round(value / step).clamp(-INT32_IN_F32, INT32_IN_F32) * step

    def requantized_biases(self):
        """The int32 biases and scales `requantize_bias` computed, for `write_back`."""
        out = {}
        with torch.no_grad():
            for name, (_, _, b) in self.requant.items():
                value = run_node(b, [self.value(i, {}) for i in b.input])[0]
                step = self.bias_step(name)
                out[b.input[0]] = torch.round(value / step).clamp(-INT32_IN_F32, INT32_IN_F32).cpu().numpy().astype(np.int32)
                out[b.input[1]] = step.cpu().numpy().astype(np.float32)
        return out

    def param_groups(self, lr, relative, scale_lr=1.0):
        """Adam's groups: one at `lr`, or (relative) one per tensor at lr times the tensor's
        largest magnitude, so integer weights, int32 biases and float weights all move by
        about the same fraction of their range per step; learned scales at `scale_lr` times
        that."""
        if not relative:
            return [{"params": list(self.parameters()), "lr": lr, "base_lr": lr}]
        groups = []
        for k, p in self.params.items():
            step = lr * max(float(p.detach().abs().max()), 1e-12) * (scale_lr if k in self.scales else 1.0)
            groups.append({"params": [p], "lr": step, "base_lr": step})
        return groups
