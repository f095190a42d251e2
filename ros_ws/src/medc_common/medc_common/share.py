"""Find a package's installed data files (``share/<package>/config/*.yaml``).

Every MEDC ROS package installs its ``config/*.yaml`` into ``share/<package>/config`` (setup.py
``data_files``). :func:`config_file` looks there first, through the ament index
(``AMENT_PREFIX_PATH``, what ``source install/setup.bash`` or ``scripts/env.sh`` set) and then
the installed share folder of this Python environment, and falls back to the package's source
tree (a checkout used through ``pip install -e`` or ``PYTHONPATH``).
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path


def _ament_share(package: str) -> Path | None:
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_share_directory
    except ImportError:
        return None
    try:
        return Path(get_package_share_directory(package))
    except (PackageNotFoundError, ValueError, LookupError):
        return None


def config_candidates(package: str, name: str) -> list[Path]:
    """Where :func:`config_file` looks for ``config/<name>`` of ``package``, in order."""
    out: list[Path] = []
    share = _ament_share(package)
    if share is not None:
        out.append(share / "config" / name)
    out.append(Path(sys.prefix) / "share" / package / "config" / name)
    spec = importlib.util.find_spec(package)
    if spec is not None and spec.origin:  # the source tree this package is imported from
        out.append(Path(spec.origin).resolve().parents[1] / "config" / name)
    try:
        from medc_common.ros_env import repo_root

        out.append(repo_root() / "ros_ws" / "src" / package / "config" / name)
    except RuntimeError:
        pass
    seen: set[Path] = set()
    return [p for p in out if not (p in seen or seen.add(p))]


def config_file(package: str, name: str) -> Path:
    """The installed ``share/<package>/config/<name>``, else the one in the package's source tree.

    Returns the first candidate of :func:`config_candidates` that exists, or the last one (so an
    error message names a real place to put it) when none does.
    """
    candidates = config_candidates(package, name)
    for path in candidates:
        if path.is_file():
            return path
    return candidates[-1] if candidates else Path("config") / name
