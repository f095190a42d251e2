#!/usr/bin/env bash
# The verdicts of docs/learned-team.md that decide its goal, recomputed from the committed episode lines
# and compared byte for byte with the committed verdict files (exit 1 when one differs):
#   the 20 x 20 length rule (medc-post-cnn9-b16-end: the frozen g20-a3 file and the seed-6067 episodes),
#   the 30 x 30 length rule (medc-post-cnn9-g30: the first 40 episodes of every g30-a3 set and
#   episodes 40-139), the mismatch sweep's rule (medc-post-cnn9-prior) and the MEDC steps claim
#   (the posterior channel). The decision-cost figures are measurements (docs/reproduction/
#   learned-team/cost/), not recomputed here.
#
#   scripts/learned_team_verdicts.sh           # check
#   scripts/learned_team_verdicts.sh --write   # write the verdict files again from the episode lines
set -euo pipefail
cd "$(dirname "$0")/.."
# shellcheck disable=SC1091
source scripts/env.sh
write=0
case ${1:-} in
  --write) write=1 ;;
  "") ;;
  *) echo "usage: scripts/learned_team_verdicts.sh [--write]" >&2; exit 2 ;;
esac
L=docs/reproduction/learned-team
frozen=(python -m medc_training.radbench.verdict frozen --reference infotaxis-exact)
failed=0

check() {  # FILE, then the command whose output it holds (run from the repository root)
  local file=$1 got
  shift
  got=$("$@")
  if (( write )); then
    printf '%s\n' "$got" > "$file"
    echo "wrote $file"
  elif [[ "$got" == "$(cat "$file")" ]]; then
    echo "same  $file"
  else
    echo "DIFFERS $file" >&2
    failed=1
  fi
}

check $L/main-posterior-cnn9-b16-end/VERDICT.txt "${frozen[@]}" \
  --yardstick docs/reproduction/radbench/searchers/g20-a3.episodes.jsonl \
  $L/main-posterior-cnn9-b16-end/medc-s{0,1,2}/frozen-g20-a3.episodes.jsonl
check $L/main-posterior-cnn9-b16-end/fresh-6067/VERDICT.txt "${frozen[@]}" \
  --yardstick $L/main-posterior-cnn9-b16-end/fresh-6067/infotaxis-exact.episodes.jsonl \
  $L/main-posterior-cnn9-b16-end/fresh-6067/medc-s{0,1,2}.episodes.jsonl
check $L/yardstick-g30-40/VERDICT-medc-post-cnn9-g30.txt "${frozen[@]}" \
  --yardstick $L/yardstick-g30-40/infotaxis-exact.episodes.jsonl \
  $L/yardstick-g30-40/medc-post-cnn9-g30/medc-s{0,1,2}.episodes.jsonl
check $L/yardstick-g30-40-140/VERDICT-medc-post-cnn9-g30.txt "${frozen[@]}" \
  --yardstick $L/yardstick-g30-40-140/infotaxis-exact.episodes.jsonl \
  $L/yardstick-g30-40-140/medc-post-cnn9-g30/medc-s{0,1,2}.episodes.jsonl
check $L/mismatch-cnn9-prior/VERDICT.txt bash -c 'cd docs && python -m medc_training.radbench.mismatch_verdict \
  --searchers infotaxis,infotaxis-exact --reference infotaxis-exact --judge cnn9-prior \
  reproduction/learned-team/mismatch cnn9-prior=reproduction/learned-team/mismatch-cnn9-prior'
S=$L/star-posterior
check $S/STEPS.txt python -m medc_training.radbench.verdict steps --budget 900000 \
  --yardstick $L/probes/searchers.episodes.jsonl --reference infotaxis-exact \
  medc=$S/medc-s3,$S/medc-s4,$S/medc-s5 sparse=$S/sparse-s3,$S/sparse-s4,$S/sparse-s5 il=$S/il-s3,$S/il-s4,$S/il-s5
exit $failed
