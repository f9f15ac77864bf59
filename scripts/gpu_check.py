"""What `scripts/gpu-check` measures, as one JSON (written again after each part, so a part that
fails or runs out of time keeps the others): the worker's op check on CUDA; its frames/s,
steps/s and GPU busy share recovering the pruned width-0.25 v5 at 256x192 (each step eagerly,
then captured as a CUDA graph, at batch 32 and 128) and the full-size v5 at 640x480 (captured
and eager); train.py at full width and 640x480 in float32 and bf16; and, with 2 GPUs or more, DDP against
one process. Each part's time is capped (the whole check within about 10 minutes);
PDI_GPU_CHECK_ONLY=NAME,... runs the named parts alone. Figures of 2026-11-27 on an H200:
docs/results/pruning.md, "Recovery on a GPU"."""
import datetime
import json
import os
import subprocess
import sys
import tempfile
import time

import numpy as np
import torch

BIN = os.environ.get("PDI_BIN", "target/release/pdi-compile")
PSF = "calib/single_lwir_blur.npy"
W025 = "models/trained/pdinet_v5_w0.25_trained.onnx"
# PDI_GPU_CHECK_DRY=1 runs every part on the CPU with 2 steps of tiny batches: the plumbing only.
DRY = bool(os.environ.get("PDI_GPU_CHECK_DRY"))
DEVICE = "cpu" if DRY else "cuda"
ONLY = [p for p in os.environ.get("PDI_GPU_CHECK_ONLY", "").split(",") if p]
out_path = sys.argv[1]
work = tempfile.mkdtemp(prefix="gpu-check-")
result = {"date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "torch": torch.__version__,
          "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None, "gpus": torch.cuda.device_count(),
          "cpu_threads": os.cpu_count(), "parts": {}}


def save():
    with open(out_path, "w") as f:
        json.dump(result, f, indent=2)


def compile_recipe(model, passes, name, timeout):
    """`pdi-compile compile` of `model` with detect-lossless then `passes`; the report."""
    recipe = os.path.join(work, f"{name}.yaml")
    with open(recipe, "w") as f:
        f.write(f"name: {name}\nbase: detect-lossless\npasses:\n" + "".join(f"  - {p}\n" for p in passes))
    out = os.path.join(work, name)
    # In its own process group: at the time limit the torch worker goes with the compiler
    # (a worker left behind would hold the GPU through the next part).
    p = subprocess.Popen([BIN, "compile", model, "--pipeline", recipe, "--psf", PSF, "-o", out, "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        stdout, stderr = p.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, 9)
        p.communicate()
        raise
    if p.returncode != 0:
        raise RuntimeError(stderr.strip().splitlines()[-1] if stderr.strip() else f"exit {p.returncode}")
    return json.loads(stdout), out


def training(report):
    d = next(p for p in report["passes"] if p["pass"] == "recover")["details"]
    t = d["training"]
    return {k: t.get(k) for k in ("device", "ranks", "batch", "steps", "capped", "seconds", "frames_per_second", "steps_per_second", "gpu_busy_share", "cuda_graph", "held_out_loss_before", "held_out_loss_after")} | {"kept": d["kept"]}


def part(name, budget):
    """Runs the decorated part now, recording its result, its error and its seconds (only the
    parts PDI_GPU_CHECK_ONLY names, comma-separated, when it is set: a short lease spent on
    what is not measured yet)."""
    def run(fn):
        if ONLY and name not in ONLY:
            return
        t = time.time()
        try:
            result["parts"][name] = fn(budget)
        except Exception as e:  # keep the other parts
            result["parts"][name] = {"error": f"{type(e).__name__}: {e}"}
        result["parts"][name]["wall_seconds"] = round(time.time() - t, 1)
        print(name, json.dumps(result["parts"][name]), flush=True)
        save()
    return run


PRUNE = "prune: {ratio: 0.5, compensate: none}"


def recover(steps, batch, frames, devices=1, graph=True, minutes=None):
    """A recover pass; `minutes` caps the training (reported) so that a part ends in time."""
    if DRY:
        steps, batch, frames = 5, 2, 8
    cap = f", minutes: {minutes}" if minutes else ""
    return f"recover: {{steps: {steps}, batch: {batch}, frames: {frames}, device: {DEVICE}, devices: {devices}, cuda_graph: {str(graph).lower()}{cap}}}"


@part("op_check_cuda", 120)
def _(budget):
    _, out = compile_recipe(W025, [PRUNE, "cleanup"], "pruned", budget)
    frames = os.path.join(work, "frames.npy")
    np.save(frames, np.random.default_rng(0).random((2, 1, 192, 256), dtype=np.float32))
    r = subprocess.run([sys.executable, "src/torch/opcheck.py", os.path.join(out, "model.onnx"), frames, DEVICE], capture_output=True, text=True, timeout=budget, check=True)
    check = json.loads(r.stdout.strip().splitlines()[-1])
    return {"worst_op_error": max(check["ops"].values()), "ops": check["ops"], "gradients": check["gradients"]}


# At 256x192 the pruned width-0.25 v5 (28% of its MACs): each step eagerly (the worker before
# CUDA graphs, its GPU 20-33% busy at batch 8-32), then captured, at batch 32 and 128.
for name, batch, graph in (("recover_256x192_eager_b32", 32, False), ("recover_256x192_graph_b32", 32, True), ("recover_256x192_graph_b128", 128, True)):
    @part(name, 70)
    def _(budget, batch=batch, graph=graph, name=name):
        report, _ = compile_recipe(W025, [PRUNE, recover(2000, batch, 1024, graph=graph, minutes=0.5), "cleanup"], name, budget)
        return training(report)


FULL = {}


@part("export_640x480_full_size", 100)
def _(budget):
    export = os.path.join(work, "full")
    subprocess.run([sys.executable, "pdinet/export.py", "--out", export, "--width", "1.0", "--size", "640x480", "--head", "v5", "--psf", "input", "--opset", "17", "--fold", "off"],
                   cwd="models", capture_output=True, check=True, timeout=budget)
    FULL["model"] = next(os.path.join(export, f) for f in os.listdir(export) if f.endswith(".onnx"))
    return {"model": os.path.basename(FULL["model"])}


# The full-size v5 (width 1.0, 640x480) pruned to half its channels, recovered: captured and
# eager at batch 16, the time capped so that the part ends inside its budget.
for name, graph in (("recover_640x480_full_size_graph_b16", True), ("recover_640x480_full_size_eager_b16", False)):
    @part(name, 110)
    def _(budget, graph=graph, name=name):
        report, _ = compile_recipe(FULL["model"], [PRUNE, recover(400, 16, 256, graph=graph, minutes=0.75), "cleanup"], name, budget)
        return training(report)


# train.py at full width and 640x480 (batch 32, 256 frames, 2 epochs: the second is timed),
# float32 against bf16 autocast: frames/s and the GPU's busy share from its log.
for name, amp in (("train_640x480_full_width_f32", "off"), ("train_640x480_full_width_bf16", "bf16")):
    @part(name, 100)
    def _(budget, amp=amp, name=name):
        data = os.path.join(work, "train-640")
        if not os.path.exists(os.path.join(data, "dataset.yaml")):
            psf = os.path.join(work, "psf")
            subprocess.run([BIN, "psf", "simulate", "--lens", "calib/lens_single_lwir.yaml", "-o", psf], check=True, capture_output=True)
            subprocess.run([BIN, "dataset", data, "--psf", psf, "--n", "8" if DRY else "256", "--q", "90", "--seed", "1", "--min-box", "16", "--out-size", "640x480"],
                           check=True, capture_output=True)
        out = os.path.join(work, name)
        epochs, batch, n = ("1", "2", "4") if DRY else ("2", "32", "256")
        p = subprocess.run([sys.executable, "models/pdinet/train.py", "--head", "v5", "--width", "0.0625" if DRY else "1.0", "--size", "640x480",
                            "--data", data, "--eval", data, "--limit", n, "--epochs", epochs, "--batch", batch, "--eval-every", "100",
                            "--amp", amp, "--device", DEVICE, "--psf", PSF, "--out", out],
                           capture_output=True, text=True, timeout=budget)
        if p.returncode != 0:
            raise RuntimeError(p.stderr.strip().splitlines()[-1] if p.stderr.strip() else f"exit {p.returncode}")
        log = [json.loads(l) for l in p.stdout.splitlines() if l.startswith("{")]
        return {"epochs": log, "frames_per_second": log[-1].get("frames_per_second"), "gpu_busy_share": log[-1].get("gpu_busy_share")}


@part("ddp_against_one_process", 150)
def _(budget):
    if torch.cuda.device_count() < 2 and not DRY:
        return {"skipped": "one GPU: NCCL needs a GPU per rank (the CPU test holds 2 gloo ranks to one process)"}
    weights, kept = [], []
    for devices in (1, 2):
        report, out = compile_recipe(W025, [PRUNE, recover(50, 16, 256, devices), "cleanup"], f"ddp{devices}", budget / 2)
        import onnx
        from onnx import numpy_helper
        kept.append(training(report)["kept"])
        m = onnx.load(os.path.join(out, "model.onnx"))
        weights.append(np.concatenate([numpy_helper.to_array(t).ravel().astype(np.float64) for t in m.graph.initializer if t.data_type == 1]))
    # Compared as compiled: when the held-out rule refuses both trainings, both are the pruned
    # model untrained and the comparison says nothing (hence `kept`).
    return {"weights_rel_l2": float(np.linalg.norm(weights[0] - weights[1]) / np.linalg.norm(weights[0])), "kept": kept}


print(json.dumps(result, indent=2))
