#!/usr/bin/env bash
# The probes of docs/learned-team.md: one training seed, one variable at a time, on the benchmark's
# world (medc-train --world radbench), each bundle and the classical searchers played on the
# validation episodes (a set file of the benchmark's generator at seed 4043, never the frozen sets).
# Every step writes its result under docs/reproduction/learned-team/probes/ and is skipped when the
# result exists, so an interrupted probe resumes where it stopped.
#
#   scripts/learned_team_probes.sh [STEPS]     # default 300000 training steps per probe
#
# Each training run uses one torch thread (MEDC_TRAIN_THREADS, default 1): on this 2-core machine a
# run with torch's default threads beside other work loses most of its speed to oversubscription.
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source scripts/env.sh
steps=${1:-300000}
threads=${MEDC_TRAIN_THREADS:-1}
out=docs/reproduction/learned-team/probes
val=${MEDC_VALIDATION_DIR:-/tmp/medc-validation}
mkdir -p "$out" "$val"
if [[ ! -s "$val/g20-a3.json" ]]; then
  medc-radbench --generate "$val" --seed 4043 --grid 20 --agents 3 --quiet > /dev/null
fi
sets="$val/g20-a3.json"
per=16  # validation episodes per set: 384 in all

play() {  # name, then policies
  local name=$1; shift
  if [[ -s "$out/$name.json" ]]; then echo "skip play $name (done)"; return; fi
  medc-radbench "$@" --sets-file "$sets" --grid 20 --agents 3 --episodes $per --quiet \
    --out "$out/$name.episodes.jsonl" > "$out/$name.json.part"
  mv "$out/$name.json.part" "$out/$name.json"
  echo "played $name"
}

train() {  # name, then medc-train arguments
  local name=$1; shift
  if [[ -s "$out/$name/policy.safetensors" ]]; then echo "skip train $name (done)"; return; fi
  local resume=()
  [[ -s "$out/$name/checkpoint.safetensors" ]] && resume=(--resume)
  medc-train --world radbench --grid 20 --agents 3 --walls 7 --max-steps 120 --steps "$steps" \
    --seed 0 --num-envs 32 --eval-every 50000 --eval-episodes 64 --no-tensorboard --quiet \
    --threads "$threads" --out "$out/$name" "${resume[@]}" "$@"
  echo "trained $name"
}

play searchers --reference infotaxis-exact infotaxis-exact infotaxis random
train sparse-300k --method sparse
train medc-infotaxis-300k --method medc --expert controller:infotaxis
# The yardstick itself as the expert (the addendum's last probe, about five times plain infotaxis's
# cost per guided step).
train medc-infotaxis-exact-300k --method medc --expert controller:infotaxis-exact
# Each bundle alone (the searchers' episodes above are the same episodes and count noise; the
# comparison pairs them by episode: python -m medc_training.radbench.pairing
# --reference infotaxis-exact DIR/*.episodes.jsonl).
for name in sparse-300k medc-infotaxis-300k medc-infotaxis-exact-300k; do
  play "bundle-$name" "$out/$name/policy.safetensors"
done
