"""What every MEDC console script shares: its ``--help`` layout, the meaning of ``--quiet`` and
progress bars that suit a terminal and a log file alike.

- :class:`HelpFormatter`: argparse's ``ArgumentDefaultsHelpFormatter`` (each option's default in
  its help, unless the help already says it or there is none to show) that keeps the layout of a
  multi-line epilog (the examples of a module docstring).
- :data:`QUIET_HELP`: ``--quiet`` means the same in medc-train, medc-launch, medc-demo,
  medc-clone and medc-record: print only the final result (the last JSON line) and errors; no
  progress bars, no per-episode or per-step lines.
- :func:`progress_bar`: a tqdm bar that redraws at most every second on a terminal and, when
  stderr is not a terminal (a log file, CI), at most every ``MEDC_PROGRESS_INTERVAL`` seconds
  (default 60), so a log holds a line a minute instead of hundreds of ``\\r`` updates.
"""

from __future__ import annotations

import argparse
import os
import sys

QUIET_HELP = "print only the final result (its JSON line) and errors: no progress bars, no per-episode lines"
#: Seconds between two redraws of a progress bar whose output is not a terminal.
NON_TTY_INTERVAL_S = 60.0


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """``ArgumentDefaultsHelpFormatter`` that leaves out defaults that say nothing (None, False)
    or that the help already states, and keeps the description's and epilog's line breaks."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("%(default)" in text or "default" in text.lower() or action.default in (None, False)
                or action.default is argparse.SUPPRESS or not action.option_strings):
            return text
        return f"{text} (default: %(default)s)" if text else "(default: %(default)s)"


def epilog(doc: str | None) -> str | None:
    """A module docstring without its first paragraph (the parser's description): the examples
    and notes, so that ``--help`` prints the description once."""
    parts = (doc or "").strip().split("\n\n", 1)
    return parts[1] if len(parts) > 1 else None


def is_terminal(stream=None) -> bool:
    """Whether ``stream`` (default stderr, where tqdm writes) is an interactive terminal."""
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


def progress_bar(total: int | None = None, *, file=None, **kwargs):
    """A tqdm bar for ``total`` units (see the module docstring for when it redraws)."""
    from tqdm import tqdm

    out = sys.stderr if file is None else file
    if is_terminal(out):
        kwargs.setdefault("mininterval", 1.0)
        kwargs.setdefault("dynamic_ncols", True)
    else:
        try:
            interval = float(os.environ.get("MEDC_PROGRESS_INTERVAL", NON_TTY_INTERVAL_S))
        except ValueError:
            interval = NON_TTY_INTERVAL_S
        kwargs["mininterval"] = max(interval, float(kwargs.get("mininterval", 0.0)))
        kwargs["maxinterval"] = max(kwargs["mininterval"], float(kwargs.get("maxinterval", 0.0)))
        kwargs.pop("dynamic_ncols", None)
        kwargs.setdefault("ncols", 100)
    return tqdm(total=total, file=out, **kwargs)
