#!/usr/bin/env bash
# The reliability study of the declaration rule (python -m medc_lab.cli.calibrate), every
# configuration of docs/reproduction/calibration/README.md. Usage: [SENSINGS="realistic"] run_study.sh OUT_PREFIX [EPISODES]
# -> OUT_PREFIX.jsonl (one record per configuration) and OUT_PREFIX.txt (the tables).
set -euo pipefail
out=$1
episodes=${2:-1000}
rm -f "$out.jsonl" "$out.txt"
for sensing in ${SENSINGS:-realistic paper-simple}; do
  for grid in 20 13 30; do
    for policy in infotaxis greedy random; do
      python -m medc_lab.cli.calibrate "$policy" --sensing "$sensing" --grid "$grid" --walls 2 \
        --episodes "$episodes" --threads 1 --out "$out.jsonl" >> "$out.txt"
    done
  done
done
