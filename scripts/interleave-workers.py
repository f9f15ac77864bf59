"""Two versions of the recovery worker on one job, interleaved: frames/s of each, and whether
they trained the same bytes (a CPU check of a worker change).

  scripts/interleave-workers.py JOB STEPS ROUNDS

JOB is a recovery job folder copied from a running `recover` (its scratch folder: config.json,
student.onnx, teacher.onnx, frames.npy, held_out.npy) plus `old_worker.py` (e.g. `git show
3348baa:src/prune/recover_worker.py`) and `new/` (a copy of src/torch/*.py). Runs with
PDI_TORCH_PYTHON (default: this Python).
"""
import json, os, subprocess, sys, statistics
job = sys.argv[1]
cfg = json.load(open(f"{job}/config.json"))
steps = int(sys.argv[2]) if len(sys.argv) > 2 else 60
rounds = int(sys.argv[3]) if len(sys.argv) > 3 else 3
res = {"old": [], "new": []}
PY = os.environ.get("PDI_TORCH_PYTHON", sys.executable)
for r in range(rounds):
    for name in (["old", "new"] if r % 2 == 0 else ["new", "old"]):
        c = dict(cfg, steps=steps, out=f"{job}/out_{name}.onnx", outputs_to=None,
                 student=f"{job}/student.onnx", teacher=f"{job}/teacher.onnx", frames=f"{job}/frames.npy", held_out=f"{job}/held_out.npy")
        json.dump(c, open(f"{job}/cfg_{name}.json", "w"))
        script = f"{job}/old_worker.py" if name == "old" else f"{job}/new/trainer.py"
        out = subprocess.run([PY, script, "train", f"{job}/cfg_{name}.json"], capture_output=True, text=True, check=True).stdout
        done = [json.loads(l) for l in out.splitlines() if l.startswith("{") and json.loads(l).get("event") == "done"][0]
        res[name].append(done["frames_per_second"])
        print(r, name, round(done["frames_per_second"], 2), "fps", done["steps"], "steps", round(done["seconds"], 1), "s", flush=True)
old, new = statistics.median(res["old"]), statistics.median(res["new"])
same = open(f"{job}/out_old.onnx", "rb").read() == open(f"{job}/out_new.onnx", "rb").read()
print(json.dumps({"identical_weights": same, "old_fps": res["old"], "new_fps": res["new"], "median_old": old, "median_new": new, "new_over_old": new / old}))
