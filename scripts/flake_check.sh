#!/usr/bin/env bash
# Flake check: run the timing-dependent tests (pytest marker `timing`: they start ROS graphs,
# processes or servers and wait on them, or measure time) RUNS times, each run a fresh pytest
# session, while one core is kept busy by a spinning process, and print each test's pass count.
#
#   scripts/flake_check.sh                      # 10 runs of every `timing` test
#   scripts/flake_check.sh -n 3 tests/ros/test_live_view.py
#   scripts/flake_check.sh --no-busy -k two_teams
#
# Arguments after the options go to pytest (files, -k, ...). The exit status is 0 only when every
# selected test passed in every run. Run it before resolving any change to ROS code or tests and
# quote its table. Each run's JUnit XML and log are kept under $FLAKE_OUT (default
# flake-check-out/).
set -euo pipefail
cd "$(dirname "$0")/.."

runs=10
busy=1
while [[ $# -gt 0 ]]; do
  case "$1" in
    -n|--runs) runs="$2"; shift 2 ;;
    --no-busy) busy=0; shift ;;
    -h|--help) sed -n '2,14p' "$0" | sed 's/^# \{0,1\}//'; exit 0 ;;
    *) break ;;
  esac
done
if ! [[ "$runs" =~ ^[1-9][0-9]*$ ]]; then
  echo "flake_check: -n needs a positive number of runs, got '$runs'" >&2
  exit 2
fi
if [[ ! -x .venv/bin/python ]]; then
  echo "flake_check: no .venv here; run 'make setup' (scripts/setup.sh) first" >&2
  exit 2
fi
# shellcheck disable=SC1091
source scripts/env.sh

out="${FLAKE_OUT:-flake-check-out}"
rm -rf "$out"
mkdir -p "$out"
spinner=""
cleanup() { [[ -n "$spinner" ]] && kill "$spinner" 2>/dev/null || true; }
trap cleanup EXIT
if [[ $busy == 1 ]]; then
  python -c "while True: pass" &
  spinner=$!
  echo "flake_check: one core kept busy (pid $spinner)"
fi

start=$(date +%s)
for ((i = 1; i <= runs; i++)); do
  t0=$(date +%s)
  set +e
  python -m pytest -m timing -p no:cacheprovider -q -o addopts="--strict-markers" \
    --junitxml="$out/run$i.xml" "$@" >"$out/run$i.log" 2>&1
  rc=$?
  set -e
  if [[ $rc -ne 0 && $rc -ne 1 ]]; then
    echo "flake_check: pytest exited $rc in run $i (not a test failure); see $out/run$i.log" >&2
    tail -20 "$out/run$i.log" >&2
    exit 2
  fi
  echo "flake_check: run $i/$runs: $(tail -1 "$out/run$i.log") ($(( $(date +%s) - t0 )) s)"
done

python - "$out" "$runs" "$(( $(date +%s) - start ))" "$busy" <<'EOF'
import json
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

out, runs, seconds, busy = Path(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "1"
counts: dict[str, dict[str, int]] = {}
for i in range(1, runs + 1):
    for case in ET.parse(out / f"run{i}.xml").iter("testcase"):
        name = f"{case.get('classname', '').replace('.', '/')}.py::{case.get('name')}"
        c = counts.setdefault(name, {"passed": 0, "failed": 0, "skipped": 0})
        if case.find("failure") is not None or case.find("error") is not None:
            c["failed"] += 1
        elif case.find("skipped") is not None:
            c["skipped"] += 1
        else:
            c["passed"] += 1
width = max((len(n) for n in counts), default=10)
print(f"\n{'test':<{width}}  passed/runs")
for name, c in sorted(counts.items()):
    mark = "" if c["failed"] == 0 else "   <-- FLAKY" if c["passed"] else "   <-- FAILS"
    print(f"{name:<{width}}  {c['passed']:>2}/{runs}{' (%d skipped)' % c['skipped'] if c['skipped'] else ''}{mark}")
bad = sorted(n for n, c in counts.items() if c["failed"])
print(f"\n{len(counts) - len(bad)} of {len(counts)} tests passed every run "
      f"({runs} runs, {'one core busy' if busy else 'idle machine'}, {seconds} s)")
print(json.dumps({"runs": runs, "busy_core": busy, "seconds": seconds, "tests": len(counts),
                  "failing": bad, "counts": counts}))
sys.exit(1 if bad or not counts else 0)
EOF
