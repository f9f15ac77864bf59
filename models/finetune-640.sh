#!/usr/bin/env bash
# The width-0.25 models at the camera's 640x480: each 256x192 model fine-tuned from its own
# weights on random 256x192 crops of 640x480 frames (a step costs what a 256x192 step costs;
# the blur map is cut with each crop), then scored with `pdi-compile verify` on the held-out
# scenes of scripts/eval-set kept at 640x480, and its card written. Checkpointed: run it again
# with `-- --resume` to continue an interrupted run.
#   models/finetune-640.sh OUT [HEAD...] [-- extra train.py arguments]
#   PDI_BIN     pdi-compile binary (default target/release/pdi-compile)
#   EPOCHS (6), LR (0.004), THREADS per head (1: the heads train side by side)
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: models/finetune-640.sh OUT [v5] [v8] [-- train.py args]}; shift
heads=(); while [ $# -gt 0 ] && [ "$1" != "--" ]; do heads+=("$1"); shift; done
[ $# -gt 0 ] && shift
[ ${#heads[@]} -gt 0 ] || heads=(v5 v8)
bin=${PDI_BIN:-target/release/pdi-compile}
epochs=${EPOCHS:-6} lr=${LR:-0.004} threads=${THREADS:-1}
. scripts/setup
mkdir -p "$out"
[ -f "$out/psf/psfs.npy" ] || "$bin" psf simulate --lens calib/lens_single_lwir.yaml -o "$out/psf" >/dev/null
# The training scenes of models/train-models.sh (seed 1) and the held-out ones (seed 2), kept
# at the sensor's 640x480.
[ -f "$out/train-640x480/dataset.yaml" ] || "$bin" dataset "$out/train-640x480" --psf "$out/psf" --n 3000 --q 90 --seed 1 --min-box 16 --out-size 640x480 >/dev/null
[ -f "$out/eval-640x480/dataset.yaml" ] || "$bin" dataset "$out/eval-640x480" --psf "$out/psf" --n 200 --q 90 --seed 2 --min-box 16 --out-size 640x480 >/dev/null
scripts/setup-toolkit
python=${PDI_TORCH_PYTHON:-$PDI_CACHE/rknn-env/bin/python}
pids=()
for head in "${heads[@]}"; do
  "$python" models/pdinet/train.py --head "$head" --width 0.25 --size 640x480 --crop 256x192 \
    --init "models/trained/pdinet_${head}_w0.25_trained.onnx" --lr "$lr" --epochs "$epochs" --batch 16 \
    --threads "$threads" --eval-every 2 --data "$out/train-640x480" --eval "$out/eval-640x480" \
    --psf calib/single_lwir_blur.npy --out "$out/$head" --name "pdinet_${head}_w0.25_640x480" "$@" > "$out/$head.log" 2>&1 &
  pids+=($!)
done
status=0
for p in "${pids[@]}"; do wait "$p" || status=1; done
[ $status -eq 0 ] || { echo "finetune-640: training failed; see $out/*.log" >&2; exit 1; }
for head in "${heads[@]}"; do
  model="$out/$head/pdinet_${head}_w0.25_640x480_trained.onnx"
  "$bin" verify --reference "$model" --candidate "$model" --data "$out/eval-640x480/degraded" \
    --psf calib/single_lwir_blur.npy --runs 0 --no-tract --json > "$out/$head/verify.json"
  "$PDI_PYTHON" - "$model" "$out/$head/pdinet_${head}_w0.25_640x480_training.json" "$out/$head/verify.json" "$head" <<'EOF'
import json, os, sys
model, training, verify, head = sys.argv[1:]
t, v = json.load(open(training)), json.load(open(verify))
lab = v["detection"]["reference_vs_labels"]
a = t["args"]
card = {
    "model": os.path.basename(model),
    "head": {"v5": "yolov5-anchor", "v8": "yolov8-dfl"}[head],
    "width": a["width"],
    "input": [1, 1, 480, 640],
    "eval_frames": v["frames"],
    "map50": round(lab["map50"], 4),
    "map50_95": round(lab["map50_95"], 4),
    "evaluated_with": "pdi-compile verify (ONNX Runtime) on scripts/eval-set's scenes (seed 2) at 640x480",
    "training": {"fine_tuned_from": os.path.basename(a["init"]), "crop": a["crop"], "epochs": a["epochs"], "lr": a["lr"],
                 "batch": a["batch"], "train_frames": t["train_frames"], "minutes": t["minutes"], "device": t["device"],
                 "torch": t["torch"], "command": "models/finetune-640.sh OUT " + head},
}
out = os.path.join(os.path.dirname(model), f"pdinet_{head}_w0.25_640x480.card.json")
json.dump(card, open(out, "w"), indent=1)
print(f"{head}: mAP@0.5 {card['map50']:.4f}, mAP@0.5:0.95 {card['map50_95']:.4f} -> {out}")
EOF
done
