"""``python -m medc_lab.cli.regimes play|report``: the claims protocol's regime probes
(:mod:`medc_lab.studies.regime_probes`): ``play`` plays what is missing (one JSON per regime and policy under
``--out``; finished ones are skipped, so it resumes), ``report`` prints the table (success rate and
mean episode length with 95% CIs)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import torch

from ..studies.regime_probes import EPISODES, EVAL_SEED, POLICIES, REGIMES, parse_regime, play, summary


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_lab.cli.regimes",
                                description="Regime probes for the claims protocol: where is reward rare, "
                                            "and how good are the classical controllers?",
                                formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("command", choices=("play", "report"))
    p.add_argument("--out", type=Path, default=Path("docs/reproduction/claims/probes"))
    p.add_argument("--regime", action="append", help="only these regimes, e.g. g40w2t100 (repeatable)")
    p.add_argument("--policy", action="append", choices=POLICIES, help="only these policies (repeatable)")
    p.add_argument("--episodes", type=int, default=EPISODES, help="fixed episodes per regime and policy")
    p.add_argument("--eval-seed", type=int, default=EVAL_SEED, help="seed of the fixed episodes")
    p.add_argument("--threads", type=int, default=1, help="torch threads")
    args = p.parse_args(argv)
    torch.set_num_threads(args.threads)
    try:
        regimes = [parse_regime(r) for r in args.regime] if args.regime else list(REGIMES)
    except ValueError as exc:
        p.error(str(exc))
    policies = args.policy or list(POLICIES)
    if args.command == "play":
        for regime in regimes:
            for policy in policies:
                path = args.out / regime.name / f"{policy}.json"
                if path.exists():
                    continue
                record = play(regime, policy, args.episodes, args.eval_seed)
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_text(json.dumps(record) + "\n")
                s = summary(record)
                print(f"{regime.name} {policy}: {s['success']:.0%} found, {s['length']:.1f} steps "
                      f"({record['seconds']:.0f} s)", flush=True)
        return 0
    print(f"| regime | {' | '.join(policies)} |")
    print(f"| --- |{' --- |' * len(policies)}")
    for regime in regimes:
        cells = []
        for policy in policies:
            path = args.out / regime.name / f"{policy}.json"
            if not path.exists():
                cells.append("not run")
                continue
            s = summary(json.loads(path.read_text()))
            cells.append(f"{s['success']:.0%} ± {s['success_ci']:.0%}, "
                         f"{s['length']:.1f} ± {s['length_ci']:.1f}")
        print(f"| {regime.name} | {' | '.join(cells)} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
