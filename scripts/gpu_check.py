"""What `scripts/gpu-check` measures, as one JSON (written again after each part, so a part that
fails or runs out of time keeps the others): the worker's op check on CUDA, its frames/s, steps/s
and GPU busy share recovering the pruned width-0.25 v5 at 256x192 and the full-size v5 at
640x480, and, with 2 GPUs or more, DDP against one process."""
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
    r = subprocess.run([BIN, "compile", model, "--pipeline", recipe, "--psf", PSF, "-o", out, "--json"], capture_output=True, text=True, timeout=timeout)
    if r.returncode != 0:
        raise RuntimeError(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}")
    return json.loads(r.stdout), out


def training(report):
    d = next(p for p in report["passes"] if p["pass"] == "recover")["details"]
    t = d["training"]
    return {k: t.get(k) for k in ("device", "ranks", "steps", "seconds", "frames_per_second", "steps_per_second", "gpu_busy_share", "held_out_loss_before", "held_out_loss_after")} | {"kept": d["kept"]}


def part(name, budget):
    """Runs the decorated part now, recording its result, its error and its seconds."""
    def run(fn):
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


def recover(steps, batch, frames, devices=1):
    if DRY:
        steps, batch, frames = 2, 2, 8
    return f"recover: {{steps: {steps}, batch: {batch}, frames: {frames}, device: {DEVICE}, devices: {devices}}}"


@part("op_check_cuda", 120)
def _(budget):
    _, out = compile_recipe(W025, [PRUNE, "cleanup"], "pruned", budget)
    frames = os.path.join(work, "frames.npy")
    np.save(frames, np.random.default_rng(0).random((2, 1, 192, 256), dtype=np.float32))
    r = subprocess.run([sys.executable, "src/torch/opcheck.py", os.path.join(out, "model.onnx"), frames, DEVICE], capture_output=True, text=True, timeout=budget, check=True)
    check = json.loads(r.stdout.strip().splitlines()[-1])
    return {"worst_op_error": max(check["ops"].values()), "ops": check["ops"], "gradients": check["gradients"]}


@part("recover_256x192", 150)
def _(budget):
    report, _ = compile_recipe(W025, [PRUNE, recover(300, 32, 1024), "cleanup"], "w025", budget)
    return training(report)


@part("recover_640x480_full_size", 240)
def _(budget):
    export = os.path.join(work, "full")
    subprocess.run([sys.executable, "pdinet/export.py", "--out", export, "--width", "1.0", "--size", "640x480", "--head", "v5", "--psf", "input", "--opset", "17", "--fold", "off"],
                   cwd="models", capture_output=True, check=True, timeout=budget)
    model = next(os.path.join(export, f) for f in os.listdir(export) if f.endswith(".onnx"))
    report, _ = compile_recipe(model, [PRUNE, recover(60, 8, 128), "cleanup"], "full", budget)
    return training(report)


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
