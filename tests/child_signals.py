"""Children that a test stops with SIGINT get the default SIGINT disposition: a test session started
in the background (nohup, some CI runners) hands its children SIGINT ignored, and Python then
installs no KeyboardInterrupt handler, whereas a user's terminal gives the default."""

from __future__ import annotations

import signal


def default_sigint() -> None:
    """``preexec_fn`` for :class:`subprocess.Popen`: SIGINT back to its default in the child."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)
