"""`medc-train`: one training run of any method, with metrics, TensorBoard, bundle and curve.

Examples::

    medc-train --env target_localization --agents 3 --walls 2 --grid 10 --method sparse \\
        --steps 100000 --out runs/a3w2-sparse
    medc-train --agents 3 --walls 2 --grid 10 --method medc \\
        --expert models/experts/A1W0.safetensors --expert models/experts/A1W3.safetensors \\
        --steps 100000 --out runs/a3w2-medc
    medc-train --method medc --expert random --expert biased:2 --expert malicious:oracle ...
    medc-train --method frl --frl-users A1W0,A3W0,A2W1,A2W2,A2W3,A3W1,A3W2,A3W3 ...
    medc-train ... --out runs/a3w2-medc --resume      # continue a killed run
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys

from ..config import METHODS, SCALES, scaled_config
from ..envs.tl_observation import DEFAULT_OBSERVATION

USER_RE = re.compile(r"^A(\d+)W(\d+)(?::(random|biased|malicious))?$")


def parse_users(text: str) -> list[dict]:
    """``A1W0,A3W2:malicious,...`` -> FRL user dicts (agents, walls, optional fault)."""
    users = []
    for token in filter(None, (t.strip() for t in text.split(","))):
        m = USER_RE.match(token)
        if not m:
            raise ValueError(f"FRL user {token!r} is not AyWz or AyWz:fault "
                             "(fault: random, biased, malicious)")
        user = {"agents": int(m.group(1)), "walls": int(m.group(2))}
        if m.group(3):
            user["fault"] = m.group(3)
        users.append(user)
    return users


def parse_env_options(items: list[str]) -> dict:
    """``["customers=8", "complexity=0.5"]`` -> ``{"customers": 8, "complexity": 0.5}``."""
    options: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        try:
            number = float(value) if sep and key else None
        except ValueError:
            number = None
        if number is None or not math.isfinite(number):
            raise ValueError(f"--env-option expects KEY=NUMBER, got {item!r}")
        options[key] = int(number) if number.is_integer() and "." not in value else number
    return options


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="medc-train", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("--env", default="target_localization", help="application (default target_localization)")
    p.add_argument("--agents", type=int, default=3, help="team size (the y in AyWz)")
    p.add_argument("--walls", type=int, default=2, help="number of walls (the z in AyWz)")
    p.add_argument("--grid", type=int, help="grid side (default: the scale's, cpu 13 / paper 30)")
    p.add_argument("--max-steps", type=int, help="episode step limit (default: the scale's)")
    p.add_argument("--observation",
                   help="target-localization observation: maps (the paper's 5 maps) | maps+estimate | egoR | "
                        f"egoR+estimate (default {DEFAULT_OBSERVATION}; docs/environments.md)")
    p.add_argument("--method", choices=METHODS, default="sparse")
    p.add_argument("--expert", action="append", default=[], metavar="SPEC",
                   help="repeatable: a bundle path | random | biased[:A] | malicious:PATH | "
                        "malicious:oracle | oracle")
    p.add_argument("--expert-weight", action="append", type=float, metavar="W",
                   help="repeatable, one per --expert in the same order: its roulette-wheel weight R_S "
                        "(normalised; default: from the experts' environment attributes by the "
                        "contract's QoS rule, medc_training.qos)")
    p.add_argument("--steps", type=int, default=100_000, help="training steps (environment steps)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.safetensors")
    p.add_argument("--scale", choices=sorted(SCALES), default="cpu",
                   help="base hyperparameters (default cpu)")
    p.add_argument("--arch", help="network architecture (lenet5, convnet-small, mlp)")
    p.add_argument("--num-envs", type=int, help="environments stepped together")
    p.add_argument("--horizon", type=int, help="training steps per PPO update")
    p.add_argument("--epochs", type=int, help="PPO epochs per update")
    p.add_argument("--lr", type=float, help="Adam learning rate (default: the scale's)")
    p.add_argument("--eval-every", type=int, help="evaluate every E training steps")
    p.add_argument("--eval-steps", type=int, help="test steps per evaluation")
    p.add_argument("--eval-envs", type=int, help="environments the test steps are split over")
    p.add_argument("--eval-sampled", action="store_true",
                   help="test on actions sampled from the policy instead of its argmax")
    p.add_argument("--expert-rate", type=float, help="R_E (default 0.1)")
    p.add_argument("--q", type=float, dest="q_threshold", help="Q (default 0.05)")
    p.add_argument("--frl-users",
                   help="FRL users, e.g. A1W0,A3W0,A2W1,A2W2,A2W3,A3W1,A3W2,A3W3 (the paper's 8)")
    p.add_argument("--frl-every", type=int, help="FedAvg every K updates (default 1)")
    p.add_argument("--env-option", action="append", default=[], metavar="KEY=VALUE",
                   help="extra numeric environment option (e.g. customers=8, complexity=0.5)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = default)")
    p.add_argument("--no-tensorboard", action="store_true")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p


def config_from_args(args: argparse.Namespace):
    """The TrainConfig the parsed arguments describe."""
    overrides = {"env": args.env, "agents": args.agents, "walls": args.walls, "method": args.method,
                 "total_steps": args.steps, "seed": args.seed, "device": args.device,
                 "torch_threads": args.threads}
    for name in ("grid", "max_steps", "observation", "arch", "num_envs", "horizon", "epochs", "lr",
                 "eval_every",
                 "eval_steps", "eval_envs", "expert_rate", "q_threshold", "frl_every"):
        value = getattr(args, name)
        if value is not None:
            overrides[name] = value
    if args.eval_sampled:
        overrides["eval_greedy"] = False
    if args.frl_users:
        overrides["frl_users"] = parse_users(args.frl_users)
    env_options = parse_env_options(args.env_option)
    if env_options:
        overrides["env_options"] = env_options
    return scaled_config(args.scale, **overrides)


def make_learner(cfg, expert_specs: list[str], expert_weights: list[float] | None = None):
    """A Trainer (or an FRL group) for the config, with experts parsed from their specs and their
    R_S (``expert_weights``, one per spec; None = from the QoS rule, see medc_training.qos)."""
    import torch

    from ..experts import parse_expert
    from ..ppo import Trainer

    if cfg.method == "frl":
        if expert_specs or expert_weights:
            raise ValueError("--expert is not used by --method frl (FRL shares parameters, not actions)")
        from ..frl import FederatedGroup

        return FederatedGroup(cfg)
    if expert_specs and cfg.method not in ("medc", "il"):
        raise ValueError(f"--expert is only used by --method medc or il, not {cfg.method}")
    gen = torch.Generator().manual_seed(cfg.seed + 13)
    experts = [parse_expert(spec, generator=gen, device=cfg.device) for spec in expert_specs]
    return Trainer(cfg, experts, expert_weights)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = config_from_args(args)
        learner = make_learner(cfg, args.expert, args.expert_weight)
        from ..runner import run_training

        summary = run_training(learner, cfg, args.out, resume=args.resume, progress=not args.quiet,
                               tensorboard=not args.no_tensorboard)
    except (ValueError, FileNotFoundError) as exc:
        print(f"medc-train: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: v for k, v in summary.items() if k != "config"}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
