"""`medc-bench`: one console script, one subcommand per benchmark.

Subcommands are discovered through the ``medc_bench`` entry-point group so that packages
which depend on medc_training (the ROS nodes) can add theirs without medc_training
importing them. Each subcommand's ``main(argv)`` prints human-readable figures and ends
with one JSON line.
"""

from __future__ import annotations

import sys
from importlib.metadata import entry_points


def _subcommands() -> dict:
    return {ep.name: ep for ep in entry_points(group="medc_bench")}


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = _subcommands()
    if not argv or argv[0] in {"-h", "--help"} or argv[0] not in commands:
        names = ", ".join(sorted(commands)) or "(none installed)"
        print(f"usage: medc-bench {{{','.join(sorted(commands))}}} [options]\n  benchmarks: {names}")
        return 0 if argv[:1] in ([], ["-h"], ["--help"]) else 2
    func = commands[argv[0]].load()
    return int(func(argv[1:]) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
