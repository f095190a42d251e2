"""A ROS domain of this test process's own, claimed with a lock file, so that test sessions running
at once on one machine (pytest-xdist workers, a second pytest, the flake check beside a developer's
run) never share one: graphs on a shared domain hear each other's moves and readings."""

from __future__ import annotations

import fcntl
import os
import tempfile

#: The domains the tests use: 100-199, away from the default 0 and from lost_uav_probe's 200-229.
FIRST, COUNT = 100, 100
_held: dict[str, int] = {}


def claim_domain() -> int:
    """This process's domain: the first free one from a pid-chosen start, held (an exclusive flock on
    ``<tmp>/medc-ros-domain-<id>.lock``) until the process exits. Child processes the test starts
    inherit it through ROS_DOMAIN_ID. Raises RuntimeError when every one is held."""
    if "id" in _held:
        return _held["id"]
    start = os.getpid() % COUNT
    for k in range(COUNT):
        domain = FIRST + (start + k) % COUNT
        path = os.path.join(tempfile.gettempdir(), f"medc-ros-domain-{domain}.lock")
        try:
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW, 0o666)
        except OSError:  # another user's lock file, or a link planted at its name: not ours to use
            continue
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        _held.update(id=domain, fd=fd)
        return domain
    raise RuntimeError(f"every test ROS domain ({FIRST}-{FIRST + COUNT - 1}) is held by another test process "
                       "on this machine; wait for those sessions to end")
