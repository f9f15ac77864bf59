#!/usr/bin/env bash
# Recreates the training and held-out sets with the physics pipeline and trains the committed
# models. Checkpointed: run it again with --resume to continue an interrupted run.
#   models/train-models.sh OUT [HEAD...] [-- extra train.py arguments]
#   PDI_BIN     pdi-compile binary (default target/release/pdi-compile)
#   TRAIN_N     training frames (default 3000); WIDTH (0.25), SIZE (256x192), EPOCHS (60)
# Heads given run in parallel (on one GPU they share it; on CPU give each --threads).
set -euo pipefail
cd "$(dirname "$0")/.."
out=${1:?usage: models/train-models.sh OUT [v5] [v8] [-- train.py args]}; shift
heads=(); while [ $# -gt 0 ] && [ "$1" != "--" ]; do heads+=("$1"); shift; done
[ $# -gt 0 ] && shift
[ ${#heads[@]} -gt 0 ] || heads=(v5 v8)
bin=${PDI_BIN:-target/release/pdi-compile}
width=${WIDTH:-0.25} size=${SIZE:-256x192} epochs=${EPOCHS:-60} n=${TRAIN_N:-3000}
mkdir -p "$out"
[ -f "$out/psf/psfs.npy" ] || "$bin" psf simulate --lens calib/lens_single_lwir.yaml -o "$out/psf" >/dev/null
# Frames are simulated on the 640x480 sensor (the PSFs have their physical pixel size), then
# area-downscaled to the training size; the held-out set is the one scripts/eval-set makes.
[ -f "$out/train-$size/dataset.yaml" ] || "$bin" dataset "$out/train-$size" --psf "$out/psf" --n "$n" --q 90 --seed 1 --min-box 16 --out-size "$size" >/dev/null
[ -f "$out/eval-$size/dataset.yaml" ] || "$bin" dataset "$out/eval-$size" --psf "$out/psf" --n 200 --q 90 --seed 2 --min-box 16 --out-size "$size" >/dev/null
pids=()
for head in "${heads[@]}"; do
  python3 models/pdinet/train.py --head "$head" --width "$width" --size "$size" --epochs "$epochs" \
    --data "$out/train-$size" --eval "$out/eval-$size" --psf calib/single_lwir_blur.npy \
    --out "$out/$head-w$width" "$@" > "$out/$head-w$width.log" 2>&1 &
  pids+=($!)
done
status=0
for p in "${pids[@]}"; do wait "$p" || status=1; done
exit $status
