"""Make the project's ROS 2 message package importable, in this process and in its children.

The pip-installed ROS has no ``setup.bash``; ``source scripts/env.sh`` puts the colcon-built
``medc_interfaces`` on ``AMENT_PREFIX_PATH``, ``LD_LIBRARY_PATH`` and ``PYTHONPATH``. A console
script started without it would fail deep inside rclpy, so :func:`ensure_interfaces` finds the
build under the repository and re-executes the process with those variables set
(``LD_LIBRARY_PATH`` is only read by the dynamic loader at process start).
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

_REEXEC_MARK = "MEDC_ROS_ENV_REEXEC"

SETUP_HINT = (
    "the ROS 2 message package medc_interfaces is not built or not on the path: run "
    "`bash scripts/setup.sh` once, then `source scripts/env.sh` in this shell"
)


class RosEnvironmentError(RuntimeError):
    """The ROS 2 environment of the project is not set up (see :data:`SETUP_HINT`)."""


def repo_root() -> Path:
    """The repository root: ``$MEDC_ROOT`` when set, else the checkout this package runs from (the
    first folder above this file holding ``training/`` and ``ros_ws/``). The one finder the
    launcher, the demo and the contract compiler share.

    Raises:
        RuntimeError: MEDC_ROOT is not set and this file is not inside a checkout.
    """
    env = os.environ.get("MEDC_ROOT")
    if env:
        return Path(env)
    here = Path(__file__).resolve()
    for parent in here.parents:
        if (parent / "training").is_dir() and (parent / "ros_ws").is_dir():
            return parent
    raise RuntimeError(f"cannot find the MEDC repository above {here}; set MEDC_ROOT to the checkout")


def interfaces_prefix() -> Path:
    """Where scripts/build_interfaces.sh installs medc_interfaces."""
    return repo_root() / "ros_ws" / "install" / "medc_interfaces"


def interfaces_env(environ: dict[str, str] | None = None) -> dict[str, str]:
    """A copy of ``environ`` (default: ``os.environ``) with medc_interfaces on the ROS paths.

    Raises:
        RosEnvironmentError: the package was never built.
    """
    env = dict(os.environ if environ is None else environ)
    prefix = interfaces_prefix()
    site = sorted(prefix.glob("lib/python3*/site-packages"))
    if not site:
        raise RosEnvironmentError(f"{prefix} does not exist: {SETUP_HINT}")

    def prepend(name: str, value: str) -> None:
        parts = [p for p in env.get(name, "").split(os.pathsep) if p]
        if value not in parts:
            env[name] = os.pathsep.join([value, *parts])

    venv = Path(sys.prefix)
    prepend("AMENT_PREFIX_PATH", str(venv))
    prepend("AMENT_PREFIX_PATH", str(prefix))
    prepend("LD_LIBRARY_PATH", str(prefix / "lib"))
    prepend("PYTHONPATH", str(site[0]))
    env.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    # The ROS wheels' start-up hook (ros_wheels_bootstrapper) adds their own library folders to
    # LD_LIBRARY_PATH once per process tree; let it run again on top of ours.
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    return env


def _importable() -> bool:
    return importlib.util.find_spec("medc_interfaces") is not None


def _paths_set() -> bool:
    lib = str(interfaces_prefix() / "lib")
    return lib in os.environ.get("LD_LIBRARY_PATH", "").split(os.pathsep)


def ensure_interfaces(argv: list[str] | None = None) -> None:
    """Return when medc_interfaces can be used here; otherwise re-exec this program with it.

    Call at the top of a console script's ``main`` before importing any medc_interfaces module.
    ``argv``: the arguments to re-execute with after the interpreter (default: this process's).

    Raises:
        RosEnvironmentError: the package is not built, or re-executing did not help.
    """
    if _importable() and _paths_set():
        return
    if _importable() and importlib.util.find_spec("rclpy") is not None and not interfaces_prefix().exists():
        return  # installed some other way (e.g. a full ROS install): trust it
    if os.environ.get(_REEXEC_MARK):
        raise RosEnvironmentError(SETUP_HINT)
    env = interfaces_env()
    env[_REEXEC_MARK] = "1"
    # orig_argv keeps the interpreter options (-c CODE, -m MODULE) that sys.argv has lost.
    args = sys.orig_argv[1:] if argv is None else argv
    sys.stdout.flush()
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *args], env)


def require_interfaces() -> None:
    """:func:`ensure_interfaces` for console scripts: on failure, print what to do and exit 2."""
    try:
        ensure_interfaces()
    except RosEnvironmentError as exc:
        print(f"{Path(sys.argv[0]).name}: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
