#!/usr/bin/env bash
# The main runs of docs/learned-team.md (its addendum): `sparse`, `medc` and `il` with
# controller:infotaxis as the expert, training seeds 0, 1, 2, in the benchmark's world, carried to
# the budget in pieces with --resume. After every piece the run folder holds the run's summary,
# metrics and curve so far, `pieces.jsonl` gains a line, and the bundle of that piece
# (policy-STEPS.safetensors, not committed) plays the validation episodes (the first 16 of every set
# of the seed-4043 file, as the probes) into validation-STEPS.json and .episodes.jsonl, from which
# the protocol's steps-to-the-yardstick comparison is read; a run that reaches the budget plays the
# frozen g20-a3 episodes (the first 40 of every set, count noise run 0, as the searchers' protocol
# run) into frozen-g20-a3.episodes.jsonl, and again with its moves sampled at temperature 0.5
# (frozen-g20-a3-T0.5.*), paired later with
#   python -m medc_training.radbench.pairing --reference infotaxis-exact \
#     docs/reproduction/radbench/searchers/g20-a3.episodes.jsonl DIR/*/frozen-g20-a3.episodes.jsonl
# A piece killed half-way resumes from the run's last checkpoint; a finished step is skipped. Two
# instances side by side share the work: each run is claimed (a lock file) by the first to reach it.
#
#   scripts/learned_team_main.sh                 # every run, seed by seed
#   scripts/learned_team_main.sh sparse-s0 il-s1 # these runs (METHOD-sSEED, METHOD: sparse, medc, il,
#                                                # medc-exact: MEDC from controller:infotaxis-exact)
#
# Environment: MEDC_MAIN_BUDGET (training steps per run, default 2000000), MEDC_MAIN_PIECE (default
# 300000), MEDC_TRAIN_THREADS (torch threads per run, default 1: two runs side by side use both
# cores), MEDC_MAIN_OUT (default docs/reproduction/learned-team/main), MEDC_MAIN_TRAIN_ARGS (more
# medc-train arguments, split on spaces, e.g. "--observation ego6+estimate+posterior"),
# MEDC_MAIN_FROZEN (1, the default: a finished run plays the frozen episodes; 0: it does not, as a
# probe, which plays validation episodes only), MEDC_MAIN_INIT (a folder of finished runs: run
# METHOD-sSEED starts from FOLDER/METHOD-sSEED/policy.safetensors with --init-from),
# MEDC_MAIN_INIT_METHOD (the method whose bundles MEDC_MAIN_INIT holds, default each run's own:
# e.g. medc, so that sparse-s1 starts from FOLDER/medc-s1/policy.safetensors),
# MEDC_MAIN_SEED_OFFSET (added to the training seed, default 0: a run started from a bundle trains on
# a fresh stream of episodes), MEDC_MAIN_GRID (20, the default, or 30: the grid the runs train on,
# their validation file is drawn at and whose frozen file they play, g20-a3 with 40 episodes per set
# or g30-a3 with 12, as the searchers' protocol runs), MEDC_MAIN_STOP_AT_LEVEL (episode lines of the
# yardstick on the validation episodes, e.g. docs/reproduction/learned-team/probes/searchers.episodes.jsonl:
# a run stops at the first piece whose validation play reaches infotaxis-exact's level there, as
# `python -m medc_training.radbench.verdict steps` reads it, and plays no frozen episodes; for
# steps-to-level comparisons, which need nothing after that piece), MEDC_MAIN_ENVS (environments
# stepped together, default 32).
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source scripts/env.sh
budget=${MEDC_MAIN_BUDGET:-2000000}
piece=${MEDC_MAIN_PIECE:-300000}
threads=${MEDC_TRAIN_THREADS:-1}
out=${MEDC_MAIN_OUT:-docs/reproduction/learned-team/main}
read -r -a train_args <<< "${MEDC_MAIN_TRAIN_ARGS:-}"
frozen=${MEDC_MAIN_FROZEN:-1}
init=${MEDC_MAIN_INIT:-}
init_method=${MEDC_MAIN_INIT_METHOD:-}
seed_offset=${MEDC_MAIN_SEED_OFFSET:-0}
grid=${MEDC_MAIN_GRID:-20}
stop_at_level=${MEDC_MAIN_STOP_AT_LEVEL:-}
envs=${MEDC_MAIN_ENVS:-32}
if [[ -n $stop_at_level && ! -s $stop_at_level ]]; then
  echo "learned_team_main: MEDC_MAIN_STOP_AT_LEVEL: no episode lines at '$stop_at_level'" >&2
  exit 2
fi
case $grid in
  20) frozen_episodes=40 ;;
  30) frozen_episodes=12 ;;
  *) echo "learned_team_main: MEDC_MAIN_GRID is 20 or 30 (the benchmark's frozen files), got '$grid'" >&2
     exit 2 ;;
esac
expert=controller:infotaxis
if ! [[ "$seed_offset" =~ ^[0-9]+$ ]]; then
  echo "learned_team_main: MEDC_MAIN_SEED_OFFSET must be a non-negative integer, got '$seed_offset'" >&2
  exit 2
fi
for n in "$budget" "$piece" "$envs"; do
  if ! [[ "$n" =~ ^[1-9][0-9]*$ ]]; then
    echo "learned_team_main: budget, piece and environments must be positive integers, got '$n'" >&2
    exit 2
  fi
done
runs=("$@")
if [[ ${#runs[@]} -eq 0 ]]; then
  runs=(sparse-s0 medc-s0 il-s0 sparse-s1 medc-s1 il-s1 sparse-s2 medc-s2 il-s2
        medc-exact-s0 medc-exact-s1 medc-exact-s2)
fi
val=${MEDC_VALIDATION_DIR:-/tmp/medc-validation}
mkdir -p "$out" "$val"
if [[ ! -s "$val/g$grid-a3.json" ]]; then
  medc-radbench --generate "$val" --seed 4043 --grid "$grid" --agents 3 --quiet > /dev/null
fi

steps_done() {  # the steps a run folder's summary records (0 when none)
  python - "$1/summary.json" <<'EOF'
import json, sys
try:
    print(int(json.load(open(sys.argv[1]))["steps"]))
except FileNotFoundError:
    print(0)
EOF
}

play_once() {  # STEM MESSAGE, then medc-radbench arguments: play into STEM.episodes.jsonl and
  # STEM.json unless STEM.json exists (it is written last, so a play cut short is played again)
  local stem=$1 message=$2
  shift 2
  [[ -s "$stem.json" ]] && return 0
  medc-radbench "$@" --quiet --overwrite --out "$stem.episodes.jsonl" > "$stem.json.part"
  mv "$stem.json.part" "$stem.json"
  echo "$(date +%T) $message"
}

validate() {  # run folder: every piece's bundle that has not played the validation episodes yet
  local dir=$1 bundle steps
  for bundle in "$dir"/policy-*.safetensors; do
    [[ -e "$bundle" ]] || continue
    steps=${bundle##*/policy-}
    steps=${steps%.safetensors}
    play_once "$dir/validation-$steps" "${dir##*/}: the $steps-step bundle played the validation episodes" \
      "$bundle" --sets-file "$val/g$grid-a3.json" --grid "$grid" --agents 3 --episodes 16
  done
}

at_level() {  # run folder: true when one of its piece bundles reached the yardstick's validation level
  [[ -n $stop_at_level && -s "$1/summary.json" ]] || return 1
  python -m medc_training.radbench.verdict steps --budget "$budget" --yardstick "$stop_at_level" \
    --reference infotaxis-exact --focus run "run=$1" | tail -1 | python -c '
import json, sys
runs = json.load(sys.stdin)["runs"]["run"]
sys.exit(0 if any(r["reached"] is not None for r in runs.values()) else 1)'
}

one_run() {  # METHOD-sSEED
  local name=$1 method seed dir
  if ! [[ "$name" =~ ^(sparse|medc|il|medc-exact)-s([0-9]+)$ ]]; then
    echo "learned_team_main: a run is METHOD-sSEED with METHOD sparse, medc, il or medc-exact, got '$name'" >&2
    return 2
  fi
  method=${BASH_REMATCH[1]}
  local run_seed=${BASH_REMATCH[2]}
  seed=$(( run_seed + seed_offset ))
  dir=$out/$name
  local claim
  exec {claim}>"$out/.$name.claim"
  if ! flock -n "$claim"; then
    echo "$(date +%T) $name: another instance has it"
    exec {claim}>&-
    return 0
  fi
  local extra=()
  case $method in
    medc|il) extra=(--expert "$expert") ;;
    medc-exact) method=medc; extra=(--expert controller:infotaxis-exact) ;;
  esac
  if [[ -n $init ]]; then
    local start=$init/${init_method:-${name%-s*}}-s$run_seed/policy.safetensors
    if [[ ! -s "$start" ]]; then
      echo "learned_team_main: MEDC_MAIN_INIT: no bundle at $start" >&2
      exec {claim}>&-
      return 2
    fi
    extra+=(--init-from "$start")
  fi
  local done_steps
  done_steps=$(steps_done "$dir")
  while (( done_steps < budget )) && ! at_level "$dir"; do
    local target=$(( (done_steps / piece + 1) * piece ))
    (( target > budget )) && target=$budget
    local resume=()
    [[ -s "$dir/checkpoint.safetensors" ]] && resume=(--resume)
    local t0; t0=$(date +%s)
    echo "$(date +%T) $name: training to $target steps"
    medc-train --world radbench --grid "$grid" --agents 3 --walls 7 --max-steps 120 --steps "$target" \
      --seed "$seed" --num-envs "$envs" --eval-every 50000 --eval-episodes 64 --no-tensorboard --quiet \
      --threads "$threads" --method "$method" "${extra[@]}" "${train_args[@]}" --out "$dir" "${resume[@]}" \
      > /dev/null
    python - "$dir" "$(( $(date +%s) - t0 ))" <<'EOF' >> "$dir/pieces.jsonl"
import json, sys
s = json.load(open(f"{sys.argv[1]}/summary.json"))
print(json.dumps({"steps": s["steps"], "train_seconds": round(s["train_seconds"], 1),
                  "piece_wall_seconds": int(sys.argv[2]),
                  "eval_episode_length": s["final_episode_length"],
                  "eval_success_rate": s["final_success_rate"]}))
EOF
    done_steps=$(steps_done "$dir")
    echo "$(date +%T) $name: $done_steps steps ($(tail -1 "$dir/pieces.jsonl"))"
    cp "$dir/policy.safetensors" "$dir/policy-$done_steps.safetensors"
    validate "$dir"
  done
  # A run stopped between its last piece and that piece's bundle copy or validation play:
  if [[ ! -e "$dir/policy-$done_steps.safetensors" ]]; then
    cp "$dir/policy.safetensors" "$dir/policy-$done_steps.safetensors"
  fi
  validate "$dir"
  if at_level "$dir"; then
    echo "$(date +%T) $name: reached the yardstick's validation level at $done_steps steps; stopped"
    exec {claim}>&-
    return 0
  fi
  if [[ $frozen == 0 ]]; then
    exec {claim}>&-
    return 0
  fi
  play_once "$dir/frozen-g$grid-a3" "$name: played the frozen g$grid-a3 episodes" \
    "$dir/policy.safetensors" --grid "$grid" --agents 3 --episodes "$frozen_episodes"
  # The second decision rule (docs/learned-team.md, addendum 3): moves sampled at temperature 0.5.
  play_once "$dir/frozen-g$grid-a3-T0.5" "$name: played the frozen g$grid-a3 episodes at temperature 0.5" \
    "$dir/policy.safetensors" --grid "$grid" --agents 3 --episodes "$frozen_episodes" --temperature 0.5
  exec {claim}>&-
}

for name in "${runs[@]}"; do
  one_run "$name"
done
