"""Checks that training survives interruption: a short run killed (SIGKILL) in the middle of an
epoch and resumed with --resume logs the same per-epoch losses as an uninterrupted run.

  python pdinet/check_resume.py --data out/pdi-train --psf ../calib/single_lwir_blur.npy [--device cpu]

Prints one JSON line (the largest relative difference of any logged loss, where the kill
landed) and exits 1 when a loss differs by more than --tolerance (float noise: the GPU's and
the CPU's parallel reductions are not bit-reproducible).
"""
import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))


def train_cmd(a, out, resume=False):
    cmd = [sys.executable, os.path.join(HERE, "train.py"), "--data", a.data, "--eval", a.data, "--out", out, "--psf", a.psf,
           "--head", a.head, "--width", str(a.width), "--epochs", str(a.epochs), "--limit", str(a.limit),
           "--eval-every", "1000", "--device", a.device, "--name", "check"]
    return cmd + ["--resume"] if resume else cmd


def losses(out):
    with open(os.path.join(out, "check_training.json")) as f:
        log = json.load(f)["log"]
    return [{k: v for k, v in r.items() if k.startswith("l_")} for r in log]


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True)
    ap.add_argument("--psf", required=True)
    ap.add_argument("--head", default="v8")
    ap.add_argument("--width", type=float, default=0.0625)
    ap.add_argument("--epochs", type=int, default=3)
    ap.add_argument("--limit", type=int, default=160)
    ap.add_argument("--device", default="auto")
    ap.add_argument("--tolerance", type=float, default=1e-3)
    a = ap.parse_args()
    root = tempfile.mkdtemp(prefix="pdi-resume-")
    straight, broken = os.path.join(root, "straight"), os.path.join(root, "broken")
    t0 = time.time()
    subprocess.run(train_cmd(a, straight), check=True, stdout=subprocess.DEVNULL)
    run_s = time.time() - t0
    # Kill the second run half an epoch after its first epoch is logged (the checkpoint exists).
    p = subprocess.Popen(train_cmd(a, broken), stdout=subprocess.PIPE, text=True)
    for line in p.stdout:
        if line.startswith('{"epoch": 1,'):
            break
    time.sleep(0.5 * run_s / a.epochs * 0.6)
    p.send_signal(signal.SIGKILL)
    p.wait()
    import torch

    killed_after = torch.load(os.path.join(broken, "checkpoint.pt"), weights_only=False)["epoch"]
    subprocess.run(train_cmd(a, broken, resume=True), check=True, stdout=subprocess.DEVNULL)
    x, y = losses(straight), losses(broken)
    worst = max(abs(r[k] - s[k]) / max(abs(r[k]), 1e-12) for r, s in zip(x, y) for k in r)
    ok = len(x) == len(y) == a.epochs and killed_after < a.epochs and worst <= a.tolerance
    print(json.dumps({"epochs": a.epochs, "killed_after_epoch": killed_after, "max_rel_diff": worst, "tolerance": a.tolerance,
                      "straight": x, "resumed": y, "device": a.device, "ok": ok}))
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
