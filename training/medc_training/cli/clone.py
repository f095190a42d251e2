"""`medc-clone`: train an expert bundle by DAgger cloning of the environment's scripted oracle.

Examples::

    medc-clone --agents 1 --walls 0 --arch lenet5 --out runs/clone-A1W0 \\
        --bundle models/experts/A1W0.safetensors
    medc-clone --env fleet_coordination --agents 2 --grid 10 --max-steps 400 \\
        --env-option customers=4 --eval-sampled --out runs/clone-fleet-A2C4

Writes OUT/metrics.csv (one row per DAgger iteration: dataset size, loss, greedy and sampled
episode length), OUT/learning_curve.png, OUT/policy.safetensors and OUT/summary.json (with a
random team's episode length on the same evaluation episodes); shows progress.
See medc_training.dagger for the algorithm.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ..console import QUIET_HELP, HelpFormatter, epilog
from .train import parse_env_options


def build_parser() -> argparse.ArgumentParser:
    from ..dagger import CloneConfig

    d = CloneConfig()
    p = argparse.ArgumentParser(
        prog="medc-clone",
        description=__doc__.split("\n\n")[0],
        formatter_class=HelpFormatter,
        epilog=epilog(__doc__),
    )
    p.add_argument("--env", default=d.env, help=f"application (default {d.env})")
    p.add_argument("--agents", type=int, default=d.agents, help=f"team size (default {d.agents})")
    p.add_argument(
        "--walls", type=int, default=d.walls, help=f"walls, target localization (default {d.walls})"
    )
    p.add_argument("--grid", type=int, default=d.grid, help=f"grid side (default {d.grid})")
    p.add_argument("--observation", default=d.observation,
                   help=f"target-localization observation: maps | egoR, each optionally with +estimate, "
                        f"+posterior or +estimate+posterior (default {d.observation})")
    p.add_argument(
        "--max-steps", type=int, default=d.max_steps, help=f"episode step limit (default {d.max_steps})"
    )
    p.add_argument(
        "--env-option",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="extra numeric environment option (e.g. customers=8, complexity=0.5)",
    )
    p.add_argument("--arch", default=d.arch, help=f"network architecture (default {d.arch})")
    p.add_argument(
        "--steps",
        type=int,
        default=d.total_steps,
        help=f"environment steps of data collection (default {d.total_steps})",
    )
    p.add_argument("--num-envs", type=int, default=d.num_envs)
    p.add_argument("--rollout-len", type=int, default=d.rollout_len, help="batched steps per iteration")
    p.add_argument("--grad-steps", type=int, default=d.grad_steps, help="minibatches per iteration")
    p.add_argument(
        "--beta-decay", type=float, default=d.beta_decay, help="oracle share in iteration i: decay**i"
    )
    p.add_argument("--lr", type=float, default=d.lr)
    p.add_argument("--max-samples", type=int, default=d.max_samples, help="dataset cap (newest kept)")
    p.add_argument("--eval-episodes", type=int, default=d.eval_episodes,
                   help="fixed episodes per evaluation, each played to its end")
    p.add_argument("--eval-every", type=int, default=d.eval_every,
                   help="evaluate every E training steps (after the iteration that reaches each "
                        "multiple of E) and after the last iteration")
    p.add_argument(
        "--eval-sampled",
        action="store_true",
        help="headline evaluation on sampled actions (coverage tasks) instead of greedy",
    )
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--device", default=d.device, help="cpu or cuda")
    p.add_argument("--threads", type=int, default=d.torch_threads,
                   help="torch CPU threads (0 = torch's default)")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--bundle", help="also write the trained bundle here")
    p.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    p.add_argument("--overwrite", action="store_true", help="replace a cloning run already in OUT")
    return p


# CloneConfig fields whose command-line option has the same name (--max-steps -> max_steps).
SAME_NAME = ("env", "agents", "walls", "grid", "observation", "max_steps", "arch", "num_envs", "rollout_len",
             "grad_steps",
             "beta_decay", "lr", "max_samples", "eval_episodes", "eval_every", "seed", "device")


def config_from_args(args: argparse.Namespace):
    from ..dagger import CloneConfig

    return CloneConfig(**{name: getattr(args, name) for name in SAME_NAME},
                       env_options=parse_env_options(args.env_option), total_steps=args.steps,
                       eval_greedy=not args.eval_sampled, torch_threads=args.threads).validate()


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        from ..dagger import clone_oracle
        from ..outfiles import check_output_folder

        check_output_folder(args.out)  # before any work: a file, a device or a name too long there
        cfg = config_from_args(args)
        if (Path(args.out) / "summary.json").exists() and not args.overwrite:
            # DAgger has no checkpoint to resume: a folder holds one finished cloning run.
            raise ValueError(f"{args.out} already holds a cloning run (summary.json); give --overwrite to "
                             "replace it, or use another --out")
        summary = clone_oracle(cfg, args.out, progress=not args.quiet, bundle_to=args.bundle)
    except (ValueError, FileNotFoundError) as exc:
        print(f"medc-clone: error: {exc}", file=sys.stderr)
        return 2
    m = summary["metrics"]
    print(
        f"greedy {m['greedy_episode_length']:.1f} steps ({m['greedy_success_rate']:.0%} found), sampled "
        f"{m['sampled_episode_length']:.1f} ({m['sampled_success_rate']:.0%}), random team "
        f"{m['random_episode_length']:.1f} ({m['random_success_rate']:.0%}); wrote {args.out}",
        file=sys.stderr,
    )
    print(json.dumps({k: summary[k] for k in ("steps", "iterations", "train_seconds", "metrics")}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
