#!/usr/bin/env bash
# MDRL-sparse (the default learner) on the realistic preset: the learned runs of the realistic-search
# study (docs/environments.md, "Realistic search"). Resumable: a run with a summary.json is skipped.
set -euo pipefail
cd "$(dirname "$0")/.."
source scripts/env.sh
OUT=${OUT:-docs/reproduction/realistic/runs}
STEPS=${STEPS:-100000}
for grid in ${GRIDS:-20 30}; do
  for walls in ${WALLS:-0 2 5}; do
    for seed in 0 1 2; do
      dir=$OUT/g${grid}w${walls}/seed${seed}
      [[ -f $dir/summary.json ]] && continue
      # Several runners may share the plan: the first to take a run's lock trains it.
      mkdir -p "$OUT/.locks"
      mkdir "$OUT/.locks/g${grid}w${walls}s${seed}" 2>/dev/null || continue
      # A killed run is carried on (medc-train refuses to restart over it, and refuses to resume
      # it under another configuration).
      resume=(); [[ -f $dir/checkpoint.safetensors ]] && resume=(--resume)
      OMP_NUM_THREADS=1 medc-train --scale cpu --grid "$grid" --max-steps 100 --walls "$walls" \
        --sensing realistic --steps "$STEPS" --seed "$seed" --threads 1 --eval-every 8192 \
        --eval-envs 64 --out "$dir" "${resume[@]}" >/dev/null 2>&1
      rmdir "$OUT/.locks/g${grid}w${walls}s${seed}"
      echo "done $dir"
    done
  done
done
