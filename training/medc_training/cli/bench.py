"""`medc-bench`: one console script, one subcommand per benchmark.

Subcommands are discovered through the ``medc_bench`` entry-point group so that packages
which depend on medc_training (the ROS nodes) can add theirs without medc_training
importing them. Each subcommand's ``main(argv)`` prints human-readable figures and ends
with one JSON line.
"""

from __future__ import annotations

import ast
import importlib.util
import sys
from importlib.metadata import entry_points
from pathlib import Path


def _subcommands() -> dict:
    return {ep.name: ep for ep in entry_points(group="medc_bench")}


def _summary(ep) -> str:
    """The first line of the subcommand module's docstring, read without importing it (a ROS
    benchmark would start rclpy's import chain just to print a help line)."""
    try:
        spec = importlib.util.find_spec(ep.module)
        source = Path(spec.origin).read_text(encoding="utf-8") if spec and spec.origin else ""
        doc = ast.get_docstring(ast.parse(source)) or ""
    except (ImportError, OSError, SyntaxError, ValueError):
        doc = ""
    line = doc.strip().splitlines()[0] if doc.strip() else ""
    # "`medc-bench env`: what it measures" -> "what it measures"
    named = line.startswith(("`", "medc-bench")) and ":" in line
    return line.split(":", 1)[1].strip() if named else line


def usage(commands: dict) -> str:
    """The ``medc-bench --help`` text: what it is, each benchmark with its one-line summary."""
    names = sorted(commands)
    lines = [
        f"usage: medc-bench {{{','.join(names)}}} [options]",
        "",
        "Run one of MEDC's benchmarks; each prints its figures and ends with one JSON line.",
        "",
        "benchmarks:",
    ]
    width = max((len(n) for n in names), default=0)
    lines += [f"  {n.ljust(width)}  {_summary(commands[n])}" for n in names] or ["  (none installed)"]
    lines += ["", "medc-bench NAME --help shows a benchmark's options."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = _subcommands()
    if not argv or argv[0] in {"-h", "--help"} or argv[0] not in commands:
        if argv and argv[0] not in {"-h", "--help"}:
            print(f"medc-bench: unknown benchmark {argv[0]!r}", file=sys.stderr)
            print(usage(commands), file=sys.stderr)
            return 2
        print(usage(commands))
        return 0
    func = commands[argv[0]].load()
    return int(func(argv[1:]) or 0)


if __name__ == "__main__":
    raise SystemExit(main())
