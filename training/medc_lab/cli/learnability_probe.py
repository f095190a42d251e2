"""``python -m medc_lab.cli.learnability_probe``: the supervised learnability probe
(:mod:`medc_lab.probes.learnability`); progress lines, then one JSON line with the held-out accuracies."""

from __future__ import annotations

import argparse
import json

from ..probes import learnability


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m medc_lab.cli.learnability_probe",
                                description=learnability.__doc__.split("\n\n")[0])
    p.add_argument("--agents", type=int, default=1)
    p.add_argument("--walls", type=int, default=0)
    p.add_argument("--grid", type=int, default=13)
    p.add_argument("--max-steps", type=int, default=50)
    p.add_argument("--envs", type=int, default=64)
    p.add_argument("--train-steps", type=int, default=400, help="batched steps of training data")
    p.add_argument("--arch", action="append", help="architecture(s) to probe (default mlp, lenet5)")
    p.add_argument("--iterations", type=int, default=2000, help="minibatches of 256 (Adam, lr 1e-3)")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print(json.dumps(learnability.probe(args)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
