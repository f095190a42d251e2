#!/usr/bin/env bash
# The searcher comparison of docs/radbench.md ("The strongest searchers"): every run of its
# protocol, in two queues (one per core), each run's JSON (medc-radbench's last line) and its
# per-episode lines under docs/reproduction/radbench/searchers/. A run whose JSON exists is skipped,
# so an interrupted comparison resumes where it stopped.
#
#   scripts/radbench_searchers.sh            # both queues, in the background of this shell
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source scripts/env.sh
out=docs/reproduction/radbench/searchers
mkdir -p "$out"
learned=docs/reproduction/realistic/probes/g20w2-250k/seed0/policy.safetensors
base="random gradient greedy infotaxis-exact space-aware"

run() {  # name, then medc-radbench arguments
  local name=$1; shift
  if [[ -s "$out/$name.json" ]]; then echo "skip $name (done)"; return; fi
  local t0; t0=$(date +%s)
  medc-radbench "$@" --quiet --overwrite --out "$out/$name.episodes.jsonl" > "$out/$name.json.part"
  mv "$out/$name.json.part" "$out/$name.json"
  echo "$name: $(( $(date +%s) - t0 )) s"
}

queue_a() {
  run g20-a1 --reference infotaxis --grid 20 --agents 1 --episodes 40 infotaxis $base "$learned"
  run g30-a1 --reference infotaxis --grid 30 --agents 1 --episodes 12 infotaxis $base
  run g20-a1-2step --reference infotaxis --grid 20 --agents 1 --obstructions 0,3,7 --episodes 8 \
    infotaxis infotaxis-exact space-aware infotaxis-2step
}
queue_b() {
  run g20-a3 --reference infotaxis --grid 20 --agents 3 --episodes 40 infotaxis $base "$learned"
  run g20-a3-team --reference infotaxis --grid 20 --agents 3 --episodes 12 \
    infotaxis infotaxis-exact space-aware team-infotaxis team-space-aware
  run g30-a3 --reference infotaxis --grid 30 --agents 3 --episodes 12 infotaxis $base
  run g30-a3-team --reference infotaxis --grid 30 --agents 3 --episodes 4 \
    infotaxis infotaxis-exact space-aware team-infotaxis team-space-aware
}
queue_a > "$out/queue-a.log" 2>&1 &
queue_b > "$out/queue-b.log" 2>&1 &
wait
