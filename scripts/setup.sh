#!/usr/bin/env bash
# One idempotent set-up step for `make demo` and `make test`.
#   - .venv with the pinned Python dependencies (requirements.txt, constraints.txt)
#   - the project's packages installed editable into it
#   - the source estimator's native kernel (a C library, cached by its source's hash)
#   - npm tools (solc, anvil, js-ipfs) under tools/node_modules
#   - the medc_interfaces message package built with colcon into ros_ws/install
# Each stage is skipped when the inputs it was built from have not changed, so a second run
# with nothing changed takes seconds.
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
VENV=$ROOT/.venv
STAMPS=$VENV/.medc-stamps
PYTHON=${PYTHON:-python3.11}

say() { printf '\033[1m[setup]\033[0m %s\n' "$*"; }
# This machine's pip config names local wheel folders that may be absent; hide that noise only.
pip_q() { "$VENV/bin/pip" "$@" 2> >(grep -v "^WARNING: Location 'file://" >&2); }
digest() { { cat "$@" 2>/dev/null || true; } | sha256sum | cut -c1-16; }
stage_current() { [[ -f $STAMPS/$1 && "$(cat "$STAMPS/$1")" == "$2" ]]; }
mark() { mkdir -p "$STAMPS"; echo "$2" >"$STAMPS/$1"; }

if [[ ! -x $VENV/bin/python ]]; then
  say "creating $VENV"
  command -v "$PYTHON" >/dev/null || PYTHON=python3
  "$PYTHON" -m venv "$VENV"
  pip_q install -q --upgrade "pip==25.3" "setuptools==80.9.0" "wheel==0.45.1"
fi

# 1. Python dependencies
d=$(digest requirements.txt constraints.txt)
if ! stage_current pydeps "$d"; then
  say "installing pinned Python dependencies (about a minute)"
  pip_q install -q -r requirements.txt -c constraints.txt
  mark pydeps "$d"
fi

# 2. The project's own packages, editable
PKGS=(training ros_ws/src/medc_common ros_ws/src/medc_sim ros_ws/src/medc_agents ros_ws/src/medc_registry
      ros_ws/src/medc_bringup)
d=$(digest training/pyproject.toml ros_ws/src/*/setup.py ros_ws/src/*/setup.cfg)
if ! stage_current pkgs "$d"; then
  say "installing the project's packages (editable)"
  args=()
  for p in "${PKGS[@]}"; do args+=(-e "$p"); done
  pip_q install -q --no-deps --no-build-isolation "${args[@]}"
  mark pkgs "$d"
fi

# 3. The source estimator's native kernel (C), built with the system compiler into
#    ~/.cache/medc/native under its source's hash (medc_training.envs.tl_native); seconds.
if ! "$VENV/bin/python" -m medc_training.envs.tl_native >/dev/null; then
  say "the estimator's native kernel was not built (no C compiler?): the torch path will be used"
fi

# 4. npm tools (solc compiler, anvil node, js-ipfs daemon)
if [[ -f tools/package.json ]]; then
  d=$(digest tools/package.json tools/package-lock.json)
  if ! stage_current npm "$d" || [[ ! -d tools/node_modules ]]; then
    say "installing npm tools into tools/node_modules (a few minutes on a cold cache)"
    # `npm install` honours package-lock.json; `npm ci` rejects js-ipfs's optional-dependency tree.
    (cd tools && npm install --no-audit --no-fund --loglevel=error)
    mark npm "$d"
  fi
fi

# 5. ROS interface package (custom messages), built with colcon
if [[ -f scripts/build_interfaces.sh ]]; then
  d=$(digest scripts/build_interfaces.sh $(find ros_ws/src/medc_interfaces -type f 2>/dev/null | sort))
  if ! stage_current interfaces "$d" || [[ ! -d ros_ws/install/medc_interfaces ]]; then
    say "building ROS 2 interface package medc_interfaces with colcon"
    bash scripts/build_interfaces.sh
    mark interfaces "$d"
  fi
fi
say "ready"
