#!/usr/bin/env bash
# The model mismatch sweep of docs/learned-team.md: the searchers (and the policies given as
# arguments, e.g. a learned team's bundle) on the first 12 episodes of every g20-a3 set, in the
# nominal world and in each departure of the protocol. Each run's JSON and episode lines go to
# docs/reproduction/learned-team/mismatch/ (or $MISMATCH_OUT); a run whose JSON exists is skipped
# (resumable). $MISMATCH_SEARCHERS narrows the searchers when a budget calls for it (empty: only the
# bundles play, paired later with the searchers' runs by `python -m medc_training.radbench.pairing`);
# $MISMATCH_REFERENCE is the policy the others are compared with (default infotaxis-exact when it
# plays, else the first policy); $MISMATCH_PRIOR (LOW,HIGH,LEVELS) plays every policy under that
# background prior of the team's estimator (medc-radbench --prior-background; bundles trained under a
# prior play under their own without it); $MISMATCH_WORLDS narrows the worlds (e.g. "nominal
# background=80"; default all nine).
#
#   scripts/radbench_mismatch.sh [BUNDLE ...]
#   MISMATCH_SEARCHERS="infotaxis infotaxis-exact" scripts/radbench_mismatch.sh BUNDLE ...
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source scripts/env.sh
out=${MISMATCH_OUT:-docs/reproduction/learned-team/mismatch}
mkdir -p "$out"
read -r -a searchers <<< "${MISMATCH_SEARCHERS-infotaxis infotaxis-exact space-aware}"
policies=("${searchers[@]}" "$@")
if [[ ${#policies[@]} -eq 0 ]]; then
  echo "radbench_mismatch: nothing to play (no searchers and no bundles)" >&2
  exit 2
fi
reference=${MISMATCH_REFERENCE:-}
if [[ -z $reference ]]; then
  reference=${policies[0]}
  for p in "${policies[@]}"; do [[ $p == infotaxis-exact ]] && reference=infotaxis-exact; done
fi
departures=(nominal background=5 background=80 transmission=0.1 transmission=0.3 strength_scale=2
            efficiency=0.7 efficiency=1.3 position_noise=0.2)
if [[ -n ${MISMATCH_WORLDS:-} ]]; then
  read -r -a worlds <<< "$MISMATCH_WORLDS"
  for w in "${worlds[@]}"; do
    known=0
    for d in "${departures[@]}"; do [[ $w == "$d" ]] && known=1; done
    if [[ $known == 0 ]]; then
      echo "radbench_mismatch: MISMATCH_WORLDS: '$w' is not one of: ${departures[*]}" >&2
      exit 2
    fi
  done
  departures=("${worlds[@]}")
fi
prior=()
[[ -n ${MISMATCH_PRIOR:-} ]] && prior=(--prior-background "$MISMATCH_PRIOR")
for d in "${departures[@]}"; do
  name=${d//=/-}
  if [[ -s "$out/$name.json" ]]; then echo "skip $name (done)"; continue; fi
  extra=()
  [[ $d != nominal ]] && extra=(--departure "$d")
  t0=$(date +%s)
  medc-radbench --grid 20 --agents 3 --episodes 12 --reference "$reference" "${extra[@]}" "${prior[@]}" --quiet \
    --overwrite --out "$out/$name.episodes.jsonl" "${policies[@]}" > "$out/$name.json.part"
  mv "$out/$name.json.part" "$out/$name.json"
  echo "$name: $(( $(date +%s) - t0 )) s"
done
