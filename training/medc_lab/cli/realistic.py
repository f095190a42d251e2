"""``python -m medc_lab.cli.realistic evaluate|report|searchers``: the realistic-search study
(:mod:`medc_lab.studies.realistic_search`): ``evaluate`` plays what is missing (finished scenarios and
policies are skipped, so it resumes), ``report`` writes the table, the figure and the paired
comparison of every searcher against infotaxis (:mod:`medc_lab.studies.realistic_searchers`), which
``searchers`` writes alone."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import torch

from ..studies import realistic_searchers
from ..studies.realistic_search import EXTRA, evaluate, report


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_lab.cli.realistic",
                                description="The realistic-search study: the learned team against the "
                                            "classical controllers on fixed episodes.")
    p.add_argument("command", choices=("evaluate", "report", "searchers"))
    p.add_argument("--out", type=Path, default=Path("docs/reproduction/realistic"))
    p.add_argument("--policy", action="append", help="only these policies (random, gradient, greedy, "
                   "infotaxis, learned, learned-seed0, ...)")
    p.add_argument("--scenario", action="append", help="only these scenarios (g20w0, g30w5, ...)")
    p.add_argument("--probe", action="append", help="also play the probe <out>/probes/NAME/seed0 on "
                   "the --scenario given (its file: eval/<scenario>/probe-NAME.json)")
    p.add_argument("--searcher", action="append", choices=(*EXTRA, "all"),
                   help="also play this searcher or team bundle on every scenario selected, outside the "
                   "protocol's table (eval/<scenario>/NAME.json; 'all': every one)")
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    if args.command == "evaluate":
        extra = list(EXTRA) if "all" in (args.searcher or ()) else args.searcher
        written = evaluate(args.out, args.policy, args.scenario, args.probe, extra)
        print(json.dumps({"written": [str(w) for w in written]}))
    elif args.command == "searchers":
        print(json.dumps({"shortest": realistic_searchers.report(args.out)}))
    else:
        print(json.dumps({**report(args.out), "shortest": realistic_searchers.report(args.out)}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
