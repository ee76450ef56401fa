#!/usr/bin/env bash
# On a machine with a GPU: train the paper-size completion network on
# the real ColoRadar maps (RMap's train scenes, a_train = 16, validation scenes one per environment), then
# time inference one patch at a time on the Table III test scenes at a_test = 4 against the paper's Table II/VI
# (56 s for 1262 patches on an RTX 6000) and print Table III for it.
#   usage: benchmarks/gpu_complete.sh [MAPS] [OUT] [TIME_LIMIT_S]   (resume: rerun with RESUME=--resume)
set -euo pipefail
cd "$(dirname "$0")/.."
MAPS=${1:-../shared/data/coloradar_maps}
OUT=${2:-runs/models/rmap_coloradar_paper.safetensors}
LIMIT=${3:-3000}  # paper: AdamW lr 1e-5 (override with LR=...), wd 5e-5, batch 16, 100 epochs
PY=${PY:-python}
"$PY" -m pipeline train --maps "$MAPS" --size paper --device cuda --a-train 16 --a-val 4 --epochs 100 \
  --batch-size 16 --lr "${LR:-1e-5}" --lr-decay 0.9 --decay-every 20 --seed 0 --time-limit "$LIMIT" --half \
  --out "$OUT" ${RESUME:-}
"$PY" -m experiments.rmap_uppointr_table --maps "$MAPS" --checkpoint "$OUT" --scenes test --a 4 --device cuda \
  --batch-size 1 --out "${OUT%.safetensors}_table3.md"
