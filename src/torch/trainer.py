"""Recovery by distillation, for `pdi-compile`'s `recover` pass and quantization-aware training,
run in the cache's torch venv. The student (an ONNX graph run by `interpreter.py`) learns to
match the teacher's head convolutions (the logits before the decode) on unlabelled frames,
freshly augmented each batch, and the trained initializers go back into the student ONNX file
unchanged in shape. With `pseudo_labels` a YOLOv8 student also learns the teacher's detections
through the detector's own loss (`pseudo.py`).

  python trainer.py train CONFIG.json   # progress as JSON lines on stdout

Under torchrun (`python -m torch.distributed.run --nproc-per-node N trainer.py train
CONFIG.json`) the training is one DistributedDataParallel job: every rank draws the same frame
order and augmentation, takes its equal share of each batch, and normalizes the loss over the
whole batch, so the weights are one process's up to float summation order; rank 0 reports and
writes the result.
"""
import datetime
import json
import math
import os
import sys
import time

import numpy as np
import onnx
import torch
import torch.distributed as dist
import torch.nn.functional as F

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from interpreter import Graph, cone  # noqa: E402
import pseudo  # noqa: E402

# torchrun's world: this process's rank and how many train together (1: no torchrun).
RANK = int(os.environ.get("RANK", "0"))
WORLD = int(os.environ.get("WORLD_SIZE", "1"))


def head_loss(s, t, spec):
    """Distillation loss of one head convolution's output (student s, teacher t: [B, C, H, W])."""
    kind = spec["kind"]
    if kind == "v5":
        na, no = spec["anchors"], spec["outputs"]
        s, t = s.view(s.shape[0], na, no, *s.shape[2:]), t.view(t.shape[0], na, no, *t.shape[2:])
        obj = torch.sigmoid(t[:, :, 4:5])
        box = (obj * (torch.sigmoid(s[:, :, :4]) - torch.sigmoid(t[:, :, :4])) ** 2).sum() / batch_total(obj) / 4
        if spec.get("edge_weight"):
            box = box + spec["edge_weight"] / 20.0 * v5_edges(s[:, :, :4], t[:, :, :4], obj)
        return box * 20.0 + soft_bce(s[:, :, 4:], t[:, :, 4:])
    if kind in ("v8cls", "v5scores"):
        kl = soft_bce_map(s, t)
        loss = kl.mean() * 10.0
        if spec.get("foreground"):
            # The same KL where the teacher sees an object (weighted by its best class score):
            # background cells outnumber objects a hundredfold and decide the plain mean, while
            # mAP ranks the objects' scores.
            w = torch.sigmoid(t).amax(1, keepdim=True)
            loss = loss + spec["foreground"] * 10.0 * (kl.mean(1, keepdim=True) * w).sum() / batch_total(w)
        return loss
    if kind == "v5box":
        # A split YOLOv5 head's box rows: matched where the teacher sees an object.
        na = spec["anchors"]
        b, _, h, w = s.shape
        s, t = s.view(b, na, 4, h, w), t.view(b, na, 4, h, w)
        obj = spec.get("objectness")
        obj = torch.ones_like(t[:, :, :1]) if obj is None else obj
        loss = (obj * (torch.sigmoid(s) - torch.sigmoid(t)) ** 2).sum() / batch_total(obj) / 4 * 20.0
        if spec.get("edge_weight"):
            loss = loss + spec["edge_weight"] * v5_edges(s, t, obj)
        return loss
    if kind == "v8box":
        r = spec["reg_max"]
        b, _, h, w = s.shape
        ls = torch.log_softmax(s.view(b, 4, r, h, w), 2)
        pt = torch.softmax(t.view(b, 4, r, h, w), 2)
        kl = (pt * (torch.log(pt.clamp(min=1e-12)) - ls)).sum(2).mean(1, keepdim=True)  # [b, 1, h, w]
        wgt = spec["weight"] if spec.get("weight") is not None else torch.ones_like(kl)
        loss = (kl * wgt).sum() / batch_total(wgt)
        bins = torch.arange(r, dtype=s.dtype, device=s.device).view(1, 1, r, 1, 1)
        if spec.get("edge_weight"):
            # The box edges themselves (each side's expected distance, in bins): where a
            # distribution's small changes move the edge, which IoU at 0.95 feels.
            edge = ((ls.exp() - pt) * bins).sum(2).abs().mean(1, keepdim=True)
            loss = loss + spec["edge_weight"] * (edge * wgt).sum() / batch_total(wgt)
        if spec.get("iou_weight"):
            iou = shared_anchor_iou((ls.exp() * bins).sum(2), (pt * bins).sum(2))
            loss = loss + spec["iou_weight"] * ((1 - iou) * wgt).sum() / batch_total(wgt)
        return loss
    raise ValueError(kind)


def shared_anchor_iou(a, b):
    """IoU of boxes given as distances (left, top, right, bottom: [B, 4, H, W]) from one
    anchor point each pair shares: the overlap's sides are the nearer of each pair of sides."""
    near = torch.minimum(a, b)
    inter = (near[:, 0] + near[:, 2]) * (near[:, 1] + near[:, 3])
    union = (a[:, 0] + a[:, 2]) * (a[:, 1] + a[:, 3]) + (b[:, 0] + b[:, 2]) * (b[:, 1] + b[:, 3]) - inter
    return (inter / union.clamp(min=1e-6)).unsqueeze(1)


def v5_edges(s, t, obj):
    """YOLOv5 box logits' absolute error ([B, anchors, 4, H, W], weighted by `obj`): the centre
    (2 sigmoid - 0.5 cells from the cell) in grid cells, the size ((2 sigmoid)^2 anchors) as
    a log ratio, so a side's error counts the same at any distance from the teacher's."""
    centre = 2 * (torch.sigmoid(s[:, :, :2]) - torch.sigmoid(t[:, :, :2])).abs().sum(2, keepdim=True)
    size = 2 * (F.logsigmoid(s[:, :, 2:4]) - F.logsigmoid(t[:, :, 2:4])).abs().sum(2, keepdim=True)
    return (obj * (centre + size)).sum() / batch_total(obj) / 4


def soft_bce(s, t):
    """BCE against the teacher's probabilities minus its entropy: a KL, zero when they agree."""
    return soft_bce_map(s, t).mean() * 10.0


def soft_bce_map(s, t):
    """`soft_bce` per element."""
    p = torch.sigmoid(t)
    return F.binary_cross_entropy_with_logits(s, p, reduction="none") - F.binary_cross_entropy_with_logits(t, p, reduction="none")


def feature_loss(s, t, keep):
    """MSE of a student feature against the teacher's kept channels, on the teacher's scale."""
    if keep is not None:
        t = t[:, keep]
    return ((s - t) ** 2).mean() / batch_var(t).clamp(min=1e-6)


def total_loss(ss, ts, heads, features=(), pseudo_weight=0.0):
    n = len(heads)
    ts = [t[:, h["keep"]] if h.get("keep") is not None else t for t, h in zip(ts[:n], heads)] + list(ts[n:])
    total = sum(feature_loss(s, t, f["keep"]) for s, t, f in zip(ss[n:], ts[n:], features))
    ss, ts = ss[:n], ts[:n]
    for s, t, spec in zip(ss, ts, heads):
        if spec["kind"] == "v8box":
            cls = [tt for tt, sp in zip(ts, heads) if sp["kind"] == "v8cls" and tt.shape[2:] == t.shape[2:]]
            spec = dict(spec, weight=torch.sigmoid(cls[0]).amax(1, keepdim=True) if cls else None)
        if spec["kind"] == "v5box":
            sc = [(tt, sp) for tt, sp in zip(ts, heads) if sp["kind"] == "v5scores" and tt.shape[2:] == t.shape[2:]]
            if sc:
                tt, sp = sc[0]
                per = tt.view(tt.shape[0], sp["anchors"], sp["outputs"], *tt.shape[2:])
                spec = dict(spec, objectness=torch.sigmoid(per[:, :, :1]))
        total = total + head_loss(s, t, spec)
    if pseudo_weight:
        det = pseudo.loss(ss, ts, heads, batch_total)
        if det is not None:
            total = total + pseudo_weight * det
    return total


class OrtTeacher:
    """On the CPU the teacher runs on ONNX Runtime (twice as fast as torch there): a callable
    like Graph's, returning the named values as tensors. With crops its frame-shaped
    constants become inputs, fed cut to each step's window (`set_window`, as Graph's)."""

    def __init__(self, path, names, threads, strides=None):
        self.strides, self.offset = dict(strides or {}), None
        self.sess, self.full = ort_session(path, names, threads, self.strides)
        self.image = [i.name for i in self.sess.get_inputs() if i.name not in self.full][0]

    def set_window(self, offset):
        self.offset = offset

    def __call__(self, x, wanted):
        feeds = {self.image: x.cpu().contiguous().numpy()}
        for name, full in self.full.items():
            if self.offset is None:
                feeds[name] = full
            else:
                s, (y, x0) = self.strides[name], self.offset
                h, w = x.shape[-2] // s, x.shape[-1] // s
                feeds[name] = np.ascontiguousarray(full[..., y // s:y // s + h, x0 // s:x0 // s + w])
        return [torch.from_numpy(v) for v in self.sess.run(wanted, feeds)]


def ort_session(path, names, threads, strides):
    """ONNX Runtime's session of the cone of `names` for any batch size; with `strides`
    (frame-shaped constants) for any frame size too, those constants made inputs (returned
    by name, whole)."""
    import onnxruntime as ort
    from onnx import numpy_helper

    m = onnx.load(path)
    # Only the head values, for any batch size (the decode after them fixes a batch of 1).
    del m.graph.output[:]
    m.graph.output.extend(onnx.ValueInfoProto(name=n) for n in names)
    del m.graph.value_info[:]
    keep = cone(list(m.graph.node), names)
    del m.graph.node[:]
    m.graph.node.extend(keep)
    for i in m.graph.input:
        i.type.tensor_type.shape.dim[0].dim_param = "batch"
        if strides:
            i.type.tensor_type.shape.dim[2].dim_param, i.type.tensor_type.shape.dim[3].dim_param = "height", "width"
    full = {}
    for t in [t for t in m.graph.initializer if t.name in strides]:
        full[t.name] = numpy_helper.to_array(t).copy()
        m.graph.initializer.remove(t)
        dims = list(t.dims[:-2]) + [f"height/{strides[t.name]}", f"width/{strides[t.name]}"]
        m.graph.input.append(onnx.helper.make_tensor_value_info(t.name, t.data_type, dims))
    so = ort.SessionOptions()
    so.log_severity_level = 3  # the cut leaves the decode's constants unused: not worth a warning
    # ORT's workers spin after each run by default and take the cores from the torch step that
    # follows: without spinning, a pruned-v8 training step with its teacher took 133-134 ms
    # against 150-155 ms (batch 8, 2 cores, the two alternating in one session).
    so.add_session_config_entry("session.intra_op.allow_spinning", "0")
    # A fixed thread count: the teacher's sums come out the same on every run.
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    return ort.InferenceSession(m.SerializeToString(), so, providers=["CPUExecutionProvider"]), full


def crop(x, window):
    """The window (input pixels) of a [B, C, H, W] value, on the value's own grid: a feature
    at stride s keeps the rows and columns the window's pixels cover."""
    if window is None:
        return x
    sy, sx = window["frame_h"] // x.shape[-2], window["frame_w"] // x.shape[-1]
    return x[..., window["y"] // sy:(window["y"] + window["h"]) // sy, window["x"] // sx:(window["x"] + window["w"]) // sx]


def cropped_teacher(teacher, window):
    """The teacher on full frames, its values cropped to the student's window."""
    if window is None:
        return teacher
    return lambda x, wanted: [crop(v, window) for v in teacher(x, wanted)]


def random_crop(x, crops, gen, models):
    """A window of the batch's frames (one per step, on the models' coarsest grid, drawn on
    the CPU generator), with each model's frame-shaped constants cut to it."""
    step, h, w = crops["step"], crops["h"], crops["w"]
    y = int(torch.randint(0, (x.shape[-2] - h) // step + 1, (1,), generator=gen)) * step
    x0 = int(torch.randint(0, (x.shape[-1] - w) // step + 1, (1,), generator=gen)) * step
    for m in models:
        m.set_window((y, x0))
    return x[..., y:y + h, x0:x0 + w].contiguous()


def augment(x, gen):
    """Fresh photometric and geometric jitter each batch: flips, gain, offset, noise, drawn
    where the generator lives (on a GPU a CPU draw of the noise, 12 M numbers at batch 256
    and 256x192, would leave the GPU idle)."""
    b, d = x.shape[0], gen.device
    flip = torch.rand(b, generator=gen, device=d) < 0.5
    x = torch.where(flip.view(b, 1, 1, 1).to(x.device), x.flip(-1), x)
    gain = (0.85 + 0.3 * torch.rand(b, 1, 1, 1, generator=gen, device=d)).to(x.device)
    offset = (0.06 * torch.rand(b, 1, 1, 1, generator=gen, device=d) - 0.03).to(x.device)
    noise = 0.004 * torch.randn(x.shape, generator=gen, device=d).to(x.device)
    return (x * gain + offset + noise).clamp(0, 1)


def on_device(specs, dev):
    """The heads' and features' channel lists as index tensors on a GPU (indexing with a list
    copies it from the host at every step, which CUDA graph capture forbids)."""
    if dev.type == "cpu":
        return specs
    return [dict(s, keep=torch.tensor(s["keep"], device=dev)) if s.get("keep") is not None else s for s in specs]


def setup(cfg):
    """The device (CUDA when torch sees it, unless the config names one), the config's fixed
    thread count, and its seed for torch and for the returned generator (which draws on the
    CPU). On the CPU the kernels are deterministic: the same config, thread count and machine
    give the same weights, however loaded the machine is."""
    dev = torch.device(cfg.get("device") or ("cuda" if torch.cuda.is_available() else "cpu"))
    if WORLD > 1:
        if dev.type == "cuda":
            dev = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
            torch.cuda.set_device(dev)
        # A collective that waits this long has lost a rank: fail rather than hang (the
        # default is half an hour; no step of these models takes a minute).
        dist.init_process_group("nccl" if dev.type == "cuda" else "gloo", timeout=datetime.timedelta(minutes=10))
    torch.set_num_threads(int(cfg.get("threads") or os.cpu_count() or 1))
    if dev.type == "cpu":
        torch.use_deterministic_algorithms(True)
    torch.manual_seed(cfg["seed"])
    return dev, torch.Generator().manual_seed(cfg["seed"])


def train(cfg):
    dev, gen = setup(cfg)
    student_model = onnx.load(cfg["student"])
    only = set(cfg["trainable"]) if cfg.get("trainable") is not None else None
    student = Graph(student_model, weight_qmax=cfg.get("weight_qmax", 127), pin_extremes=cfg.get("pin_extremes", False),
                    weight_qmin=cfg.get("weight_qmin"), only=only, scale_groups=cfg.get("scale_groups", ())).to_device(dev)
    heads, features = on_device(cfg["heads"], dev), on_device(cfg.get("features", []), dev)
    pseudo_weight = cfg.get("pseudo_labels") or 0.0
    names = [h["value"] for h in heads] + [f["value"] for f in features]
    # The student's copy of a value where it differs (a quantized value's dequantized copy).
    student_names = [h.get("student_value") or h["value"] for h in heads] + [f["value"] for f in features]
    crops = cfg.get("crop")
    if dev.type == "cpu":
        teacher = OrtTeacher(cfg["teacher"], names, torch.get_num_threads(), crops["teacher"] if crops else None)
    else:
        teacher = Graph(onnx.load(cfg["teacher"]), trainable=False).to_device(dev).eval()
        if crops:
            teacher.crop_constants(crops["teacher"], (crops["h"], crops["w"]))
    if crops:
        student.crop_constants(crops["student"], (crops["h"], crops["w"]))
    window = cfg.get("window")
    frames = torch.from_numpy(np.load(cfg["frames"])).to(dev)
    if window is not None:
        window = dict(window, frame_h=frames.shape[-2], frame_w=frames.shape[-1])
    teacher_graph = teacher  # set_window's owner (cropped_teacher wraps it)
    teacher = cropped_teacher(teacher, window)
    student_in = (lambda x: crop(x, window))
    held = torch.from_numpy(np.load(cfg["held_out"])).to(dev)
    batch, n = cfg["batch"], len(frames)
    per_epoch = max(1, n // batch)

    def held_loss():
        student.set_window(None)
        teacher_graph.set_window(None)
        with torch.no_grad():
            tot = 0.0
            for i in range(0, len(held), batch):
                x = held[i:i + batch]
                tot += float(total_loss(student(student_in(x), student_names), teacher(x, names), heads, features, pseudo_weight)) * len(x)
            return tot / len(held)

    groups = student.param_groups(cfg["lr"], cfg.get("relative_lr", False), cfg.get("scale_lr", 1.0))
    # On one GPU the step is captured as a CUDA graph (`Captured`): Adam then keeps its state
    # and learning rates on the device, and the schedule writes the rates in place.
    # (Not with the teacher's detections as labels: their count changes from step to step.)
    graphed = dev.type == "cuda" and WORLD == 1 and cfg.get("cuda_graph", True) and not pseudo_weight
    if graphed:
        for g in groups:
            g["lr"] = torch.tensor(g["lr"], device=dev)
    opt = torch.optim.Adam(groups, capturable=graphed)
    # Under torchrun the training forward goes through DDP, which averages the ranks'
    # gradients; the held-out loss uses the module itself (every rank computes the same).
    model = student
    if WORLD > 1:
        model = torch.nn.parallel.DistributedDataParallel(student, device_ids=[dev.index] if dev.type == "cuda" else None, broadcast_buffers=False)

    ema = Ema(student, cfg["ema"], dev) if cfg.get("ema") else None

    def train_step(x):
        with torch.no_grad():
            t = teacher(x, names)
        loss = total_loss(model(student_in(x), student_names), t, heads, features, pseudo_weight)
        opt.zero_grad()
        loss.backward()
        opt.step()
        student.restore_pinned()
        if ema is not None:
            ema.update()
        return loss.detach()
    run_step = Captured(train_step, opt) if graphed else train_step
    # The augmentation draws on the device (the frame order stays the CPU generator's).
    agen = gen if dev.type == "cpu" else torch.Generator(device=dev).manual_seed(cfg["seed"])
    start, before = time.time(), held_loss()
    busy = BusySampler(dev)
    emit({"event": "start", "device": str(dev), "ranks": WORLD, "parameters": sum(p.numel() for p in student.parameters()), "held_out_loss": before, "frames": n})
    # The schedule follows the step count alone; the minutes only cap a run (reported), so
    # the same job gives the same weights whatever the machine's speed or load.
    steps, warmup = cfg["steps"], cfg.get("warmup", 0)
    cap = cfg.get("minutes")
    step, seen, curve, epoch, capped = 0, 0, [], 0, False
    while step < steps and not capped:
        # On the device once an epoch: a copy from the host at every step waits for the GPU.
        perm = torch.randperm(n, generator=gen).to(dev)
        tot, cnt = 0.0, 0
        for i in range(per_epoch):
            if step >= steps:
                break
            if cap is not None and over_cap(time.time() - start > cap * 60, dev):
                capped = True
                break
            # Every rank draws the whole batch and its augmentation (so the generator stays
            # in step with one process's), then trains on its share.
            x = augment(frames[perm[i * batch:(i + 1) * batch]], agen)
            if crops:
                x = random_crop(x, crops, gen, (student, teacher_graph))
            if WORLD > 1:
                x = x.chunk(WORLD)[RANK]
            # Linear warm-up, then cosine decay to 2% over the remaining steps.
            scale = (step + 1) / warmup if step < warmup else 0.02 + 0.98 * 0.5 * (1 + math.cos(math.pi * (step - warmup) / max(1, steps - warmup)))
            for g in opt.param_groups:
                if graphed:
                    g["lr"].fill_(g["base_lr"] * scale)
                else:
                    g["lr"] = g["base_lr"] * scale
            if ema is not None:
                ema.set_step(step)
            loss = run_step(x)
            step, seen, cnt = step + 1, seen + len(x) * WORLD, cnt + 1
            # On a GPU summed on the device (a read per step waits for it), read every 10 steps.
            tot = tot + (loss if dev.type == "cuda" else whole_batch(loss))
            if step % 10 == 0 or step == steps:
                emit({"event": "step", "step": step, "steps": steps, "loss": whole_batch(loss)})
        epoch += 1
        curve.append((whole_batch(tot) if torch.is_tensor(tot) else tot) / max(cnt, 1))
        emit({"event": "epoch", "epoch": epoch, "loss": curve[-1], "step": step, "steps": steps})
    if dev.type == "cuda":
        torch.cuda.synchronize(dev)  # the queued steps count in the time
    seconds = time.time() - start
    gpu_busy = busy.stop()
    after = held_loss()
    averaged = None
    if ema is not None:
        # The average replaces the last step's weights only where it is closer to the
        # teacher on the held-out frames.
        last = ema.swap()
        averaged = {"decay": cfg["ema"], "held_out_loss_last": after, "held_out_loss_average": held_loss()}
        averaged["kept"] = averaged["held_out_loss_average"] < after
        if averaged["kept"]:
            after = averaged["held_out_loss_average"]
        else:
            ema.restore(last)
    if RANK == 0:
        student.write_back(student_model)
        onnx.save(student_model, cfg["out"])
        if cfg.get("outputs_to"):
            save_outputs(student, student_model, held, cfg["outputs_to"])
    emit({"event": "done", "held_out_loss_before": before, "held_out_loss_after": after, "loss_per_epoch": curve, "epochs": epoch,
          "steps": step, "steps_planned": steps, "capped": capped, "seconds": seconds, "frames_per_second": seen / max(seconds, 1e-9),
          "steps_per_second": step / max(seconds, 1e-9), "gpu_busy_share": gpu_busy, "device": str(dev), "threads": torch.get_num_threads(), "ranks": WORLD, "torch": torch.__version__,
          "batch": batch, "cuda_graph": run_step.report() if graphed else None, "crop": f"{crops['w']}x{crops['h']}" if crops else None, "ema": averaged})
    if WORLD > 1:
        dist.barrier()
        dist.destroy_process_group()


class Ema:
    """An exponential moving average of the student's parameters, as YOLO trainers keep: the
    average of the late steps lands nearer the middle of the valley the last steps wander in.
    The decay ramps as (1 + step) / (10 + step) up to `decay`, so the first steps' weights
    (far from the teacher) fade quickly. On a GPU the decay is a device tensor written
    outside the captured step, as the learning rates are."""

    def __init__(self, module, decay, dev):
        self.params = list(module.parameters())
        self.avg = [p.detach().clone() for p in self.params]
        self.top = decay
        self.decay = torch.zeros((), device=dev) if dev.type == "cuda" else 0.0

    def set_step(self, step):
        d = min(self.top, (1 + step) / (10 + step))
        if torch.is_tensor(self.decay):
            self.decay.fill_(d)
        else:
            self.decay = d

    def update(self):
        with torch.no_grad():
            for a, p in zip(self.avg, self.params):
                a.mul_(self.decay).add_((1 - self.decay) * p.detach())

    def swap(self):
        """Puts the average into the parameters; returns the last step's weights."""
        with torch.no_grad():
            last = [p.detach().clone() for p in self.params]
            for a, p in zip(self.avg, self.params):
                p.copy_(a)
        return last

    def restore(self, weights):
        with torch.no_grad():
            for w, p in zip(weights, self.params):
                p.copy_(w)


class Captured:
    """A training step on one GPU, captured as a CUDA graph and replayed: one launch a step
    instead of about a thousand from Python (teacher, student, loss, backward, Adam), which
    is what kept the GPU 20-33% busy at 256x192. The first `EAGER` steps run as they are, on
    a side stream (they warm cuDNN and Adam's state; they are training steps like the
    others); the next is captured. Where capture fails, training goes on eagerly and the
    report says why."""

    EAGER = 3

    def __init__(self, step, opt):
        self.step, self.opt, self.calls = step, opt, 0
        self.graph, self.error, self.static_x, self.static_loss = None, None, None, None
        self.side = torch.cuda.Stream()

    def __call__(self, x):
        self.calls += 1
        if self.graph is not None:
            self.static_x.copy_(x)
            self.graph.replay()
            return self.static_loss.clone()
        if self.calls <= self.EAGER or self.error is not None:
            self.side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(self.side):
                loss = self.step(x)
            torch.cuda.current_stream().wait_stream(self.side)
            return loss
        try:
            self.static_x = x.clone()
            self.opt.zero_grad(set_to_none=True)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                self.static_loss = self.step(self.static_x)
            self.graph = graph
        except Exception as e:  # train on eagerly, and say why
            self.error = f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
            self.opt.zero_grad(set_to_none=True)
            torch.cuda.synchronize()
            return self(x)
        # Capture records the step without running it: this batch's step is the first replay.
        self.graph.replay()
        return self.static_loss.clone()

    def report(self):
        return {"captured": self.graph is not None, "eager_steps": self.EAGER, "error": self.error}


class BusySampler:
    """On a GPU, the share of time it was busy while training: NVML's utilization, sampled
    every 0.1 s in a thread (None on the CPU, or where NVML is not installed)."""

    def __init__(self, dev):
        self.samples, self.running, self.thread = [], True, None
        if dev.type != "cuda":
            return
        try:
            import pynvml

            pynvml.nvmlInit()
            handle = pynvml.nvmlDeviceGetHandleByIndex(dev.index or 0)
        except Exception:
            return
        import threading

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


def whole_batch(loss):
    """The loss of the whole batch, for the report: under torchrun the ranks' shares averaged."""
    if WORLD == 1:
        return float(loss)
    v = loss.detach().clone()
    dist.all_reduce(v)
    return float(v) / WORLD


def over_cap(mine, dev):
    """Whether the time cap stops training: rank 0's clock decides for every rank, so all stop
    at the same step (a rank that stopped alone would leave the others waiting)."""
    if WORLD == 1:
        return mine
    flag = torch.tensor([1.0 if mine else 0.0], device=dev)
    dist.broadcast(flag, 0)
    return bool(flag.item())


def save_outputs(g, model, frames, folder):
    """The graph outputs of the trained module, frame by frame (the decode fixes a batch of
    1), as out{k}.npy: what the written model must reproduce on ONNX Runtime."""
    names = [o.name for o in model.graph.output]
    with torch.no_grad():
        per_frame = [g(frames[i:i + 1], names) for i in range(len(frames))]
    for k in range(len(names)):
        np.save(os.path.join(folder, f"out{k}.npy"), torch.cat([f[k] for f in per_frame]).contiguous().cpu().numpy().astype(np.float32))


def emit(obj):
    if RANK == 0:
        print(json.dumps(obj), flush=True)


def batch_total(x):
    """The normalizer `x.sum().clamp(min=1)` of a loss over the whole batch. Under torchrun
    the ranks' shares are summed, and the result divided by the ranks, since DDP averages
    their gradients: the loss each rank normalizes by it sums, over the ranks, to the one
    process's loss. (Normalizers come from the teacher: no gradient flows through them.)"""
    if WORLD == 1:
        return x.sum().clamp(min=1)
    s = x.sum().detach().clone()
    dist.all_reduce(s)
    return s.clamp(min=1) / WORLD


def batch_var(t):
    """`t.var()` over the whole batch (the ranks' shares together under torchrun)."""
    if WORLD == 1:
        return t.var()
    s = torch.stack([t.sum(), (t * t).sum(), torch.tensor(float(t.numel()), device=t.device)]).detach()
    dist.all_reduce(s)
    total, squares, n = s[0], s[1], s[2]
    return (squares - total * total / n) / (n - 1)


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] != "train":
        sys.exit(f"usage: {sys.argv[0]} train CONFIG.json")
    with open(sys.argv[2]) as f:
        train(json.load(f))
