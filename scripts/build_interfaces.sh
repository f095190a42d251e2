#!/usr/bin/env bash
# Build the medc_interfaces ROS 2 message package into ros_ws/install with colcon.
# Called by scripts/setup.sh; safe to run again (the path fix is idempotent, colcon rebuilds
# only what changed).
set -euo pipefail
cd "$(dirname "$0")/.."
ROOT=$PWD
# MEDC_VENV: the virtual environment to build with (a git worktree shares its main checkout's).
VENV=${MEDC_VENV:-$ROOT/.venv}
PY=$VENV/bin/python

# The ROS wheels' exported CMake files name the include paths of the machine that built them;
# point them at this venv's Python and numpy headers or rosidl_generator_py cannot compile.
"$PY" - "$VENV/share" <<'PYEOF'
import pathlib
import sys
import sysconfig

import numpy

share = pathlib.Path(sys.argv[1])
py_inc = sysconfig.get_paths()["include"]
np_inc = numpy.get_include()
old_root = "/opt/python/cp311-cp311"
fixed = 0
for path in share.rglob("*.cmake"):
    text = path.read_text(errors="surrogateescape")
    if old_root not in text:
        continue
    new = text
    # A numpy include under the old root becomes this venv's numpy include.
    for prefix in (f"{old_root}/lib/python3.11/site-packages/numpy/_core/include",
                   f"{old_root}/lib/python3.11/site-packages/numpy/core/include"):
        new = new.replace(prefix, np_inc)
    new = new.replace(f"{old_root}/include/python3.11", py_inc)
    if old_root in new:
        # Any other path under the old root: make it visible rather than guessing.
        for line in new.splitlines():
            if old_root in line:
                print(f"[build_interfaces] warning: unrewritten path in {path}: {line.strip()}")
    path.write_text(new, errors="surrogateescape")
    fixed += 1
if fixed:
    print(f"[build_interfaces] rewrote include paths in {fixed} CMake files")
PYEOF

export VIRTUAL_ENV=$VENV
export PATH="$VENV/bin:$PATH"
export AMENT_PREFIX_PATH=$VENV
# CMake's FindPython must pick the venv's interpreter (it has numpy and the rosidl generators).
cd ros_ws
"$VENV/bin/colcon" --log-base log build \
  --packages-select medc_interfaces \
  --build-base build --install-base install \
  --event-handlers console_direct- \
  --cmake-args -DPython3_EXECUTABLE="$PY" -DPYTHON_EXECUTABLE="$PY" -DBUILD_TESTING=OFF
echo "[build_interfaces] medc_interfaces installed in $ROOT/ros_ws/install/medc_interfaces"
