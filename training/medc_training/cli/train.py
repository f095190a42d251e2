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
    medc-train ... --out runs/a3w2-medc --seeds 0 1 2  # a sweep: one run per seed in OUT/seed-N
    medc-train ... --out runs/a3w2-medc --seeds 0 1 2 --ray HEAD:6379   # ... as Ray tasks on a cluster

A sweep (``--seeds``) runs through the same engines as ``medc-reproduce``: a local process pool
(``--jobs``) or Ray (``--ray``, docs/training.md). Each seed's folder appears only when its run
has finished; rerunning the sweep skips finished seeds and resumes unfinished ones. A folder
holds one run: ``--resume`` and a rerun sweep refuse a run of another configuration (naming every
differing field), and a finished run is replaced only with ``--overwrite``.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

from ..config import METHODS, SCALES, scaled_config
from ..console import QUIET_HELP, HelpFormatter, epilog
from ..envs import DEFAULT_APPLICATION, WORLDS, application

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


def _add_evaluation_arguments(p: argparse.ArgumentParser) -> None:
    """How a run evaluates its policy while it trains."""
    p.add_argument("--eval-every", type=int, help="evaluate every E training steps")
    p.add_argument("--eval-episodes", type=int,
                   help="fixed episodes per evaluation, each played to its end (default 64); 0: the legacy "
                        "window of --eval-steps test steps, which the research harness keeps for the "
                        "committed reproduction's runs (medc-reproduce)")
    p.add_argument("--eval-steps", type=int,
                   help="test steps per evaluation on the legacy window (--eval-episodes 0)")
    p.add_argument("--eval-envs", type=int,
                   help="environments the evaluation episodes (or test steps) are split over")
    p.add_argument("--eval-sampled", action="store_true",
                   help="test on actions sampled from the policy instead of its argmax")


def build_parser() -> argparse.ArgumentParser:
    default = application(DEFAULT_APPLICATION)
    p = argparse.ArgumentParser(prog="medc-train", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter, epilog=epilog(__doc__))
    p.add_argument("--env", default=default.name, help=f"application (default {default.name})")
    p.add_argument("--agents", type=int, default=3, help="team size (the y in AyWz)")
    p.add_argument("--walls", type=int, default=2, help="number of walls (the z in AyWz)")
    p.add_argument("--grid", type=int, help="grid side (default: the scale's, cpu 13 / paper 30)")
    p.add_argument("--max-steps", type=int, help="episode step limit (default: the scale's)")
    p.add_argument("--observation",
                   help="observation: maps (the application's absolute maps) | egoR (agent-centred "
                        "windows) | for target localization also maps+estimate | egoR+estimate, and any "
                        "of these four followed by +posterior, +information or both (e.g. "
                        "ego6+estimate+posterior) (default: "
                        f"{default.default_observation} for target localization, maps for the others; "
                        "docs/environments.md)")
    p.add_argument("--sensing", choices=sorted(default.sensing_presets),
                   help="target localization's sensing model (default paper-simple; docs/environments.md)")
    p.add_argument("--world", choices=WORLDS,
                   help="target localization's world: grid (the project's layouts, default) | radbench (the "
                        "field benchmark's world on fresh episodes, docs/radbench.md; --walls is then the "
                        "most obstructions of an episode, 0-7, and --sensing realistic)")
    p.add_argument("--method", choices=METHODS, default="sparse",
                   help="sparse (MDRL, sparse reward), medc (Multi-Expert Demonstration Cloning), rs (reward "
                        "shaping), il (imitation), frl (federated averaging); default sparse")
    p.add_argument("--expert", action="append", default=[], metavar="SPEC",
                   help="repeatable: a bundle path | random | biased[:A] | malicious:PATH | "
                        "malicious:oracle | oracle | controller:NAME (a classical searcher, e.g. "
                        "controller:space-aware; medc-controllers --help)")
    p.add_argument("--expert-weight", action="append", type=float, metavar="W",
                   help="repeatable, one per --expert in the same order: its roulette-wheel weight R_S "
                        "(normalised; default: from the experts' environment attributes by the "
                        "contract's QoS rule, medc_training.qos)")
    p.add_argument("--steps", type=int, default=100_000, help="training steps (environment steps)")
    p.add_argument("--seed", type=int, default=0, help="the run's seed (default 0)")
    p.add_argument("--seeds", type=int, nargs="+", metavar="SEED",
                   help="a sweep: one run per seed into OUT/seed-SEED (instead of --seed); see --jobs, --ray")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--out", required=True, help="output directory")
    p.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.safetensors")
    p.add_argument("--init-from", metavar="BUNDLE",
                   help="start from this bundle's network (same application, observation and "
                        "architecture) with a fresh optimiser, instead of a fresh network")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a run already in OUT (refused without it; a sweep: seeds of another config)")
    p.add_argument("--scale", choices=sorted(SCALES), default="cpu",
                   help="base hyperparameters (default cpu)")
    p.add_argument("--arch", help="network architecture (lenet5, convnet-small, convnet-wide, mlp, mlp-wide)")
    p.add_argument("--num-envs", type=int, help="environments stepped together")
    p.add_argument("--horizon", type=int, help="training steps per PPO update")
    p.add_argument("--epochs", type=int, help="PPO epochs per update")
    p.add_argument("--lr", type=float, help="Adam learning rate (default: the scale's)")
    p.add_argument("--lr-anneal-steps", type=int, metavar="N",
                   help="lower the learning rate linearly to 0 at training step N (the run's whole budget "
                        "when it is trained in --resume pieces); default 0: constant")
    p.add_argument("--gamma", type=float,
                   help="discount factor γ (default 0.99, the paper's); lower values weigh each move "
                        "of a short episode more")
    _add_evaluation_arguments(p)
    p.add_argument("--expert-rate", type=float, help="R_E (default 0.1)")
    p.add_argument("--q", type=float, dest="q_threshold", help="Q (default 0.05)")
    p.add_argument("--frl-users",
                   help="FRL users, e.g. A1W0,A3W0,A2W1,A2W2,A2W3,A3W1,A3W2,A3W3 (the paper's 8)")
    p.add_argument("--frl-every", type=int, help="FedAvg every K updates (default 1)")
    p.add_argument("--env-option", action="append", default=[], metavar="KEY=VALUE",
                   help="extra numeric environment option (e.g. customers=8, complexity=0.5)")
    p.add_argument("--threads", type=int, default=0, help="torch CPU threads (0 = default)")
    p.add_argument("--no-tensorboard", action="store_true", help="write metrics.csv only (no tb/ folder)")
    p.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    from ..engines import add_engine_arguments

    add_engine_arguments(p)
    return p


def config_from_args(args: argparse.Namespace):
    """The TrainConfig the parsed arguments describe."""
    overrides = {"env": args.env, "agents": args.agents, "walls": args.walls, "method": args.method,
                 "total_steps": args.steps, "seed": args.seed, "device": args.device,
                 "torch_threads": args.threads}
    for name in ("grid", "max_steps", "observation", "arch", "num_envs", "horizon", "epochs", "lr",
                 "lr_anneal_steps", "gamma", "eval_every", "eval_episodes",
                 "eval_steps", "eval_envs", "expert_rate", "q_threshold", "frl_every"):
        value = getattr(args, name)
        if value is not None:
            overrides[name] = value
    if args.eval_sampled:
        overrides["eval_greedy"] = False
    if args.frl_users:
        overrides["frl_users"] = parse_users(args.frl_users)
    env_options = parse_env_options(args.env_option)
    app = application(args.env)
    if args.observation is not None and not app.observation_in_config:
        # Given explicitly, it reaches the core even when it is the scale's observation, so that
        # an application refuses a view it does not take.
        env_options.setdefault("observation", args.observation)
    if args.sensing is not None and args.sensing != application(DEFAULT_APPLICATION).default_sensing:
        env_options.setdefault("sensing", args.sensing)
    if args.world is not None and args.world != "grid":
        if args.sensing is None:
            env_options.setdefault("sensing", "realistic")
        env_options.setdefault("world", args.world)
    if env_options:
        overrides["env_options"] = env_options
    return scaled_config(args.scale, **overrides)


def sweep_jobs(args: argparse.Namespace) -> list[dict]:
    """One job per ``--seeds`` seed: the run medc-train would make with ``--seed N --out OUT/seed-N``."""
    from ..jobs import check_experts

    jobs = []
    for seed in dict.fromkeys(args.seeds):
        args.seed = seed
        cfg = config_from_args(args).validate()
        check_experts(cfg.method, args.expert, args.expert_weight)
        jobs.append({"name": f"seed-{seed}", "config": cfg.to_dict(), "experts": list(args.expert),
                     "expert_weights": args.expert_weight, "out": str(Path(args.out) / f"seed-{seed}"),
                     "tensorboard": not args.no_tensorboard, "save_final": True, "keep_checkpoint": True,
                     "overwrite": args.overwrite})
    return jobs


def main(argv: list[str] | None = None) -> int:
    p = build_parser()
    args = p.parse_args(argv)
    if args.seeds is None and (args.ray is not None or args.jobs is not None):
        p.error("--ray and --jobs run a sweep: give the seeds with --seeds")
    if args.seeds is not None and args.init_from is not None:
        p.error("--init-from starts one run: give one --seed (a run per seed, each with its bundle)")
    try:
        from ..outfiles import check_output_folder

        check_output_folder(args.out)  # before any work: a file, a device or a name too long there
        if args.seeds is not None:
            return _sweep(args)
        cfg = config_from_args(args)
        from ..jobs import make_learner
        from ..runner import run_training
        from ..runs import run_inputs
        from ..warmstart import init_from_bundle

        learner = make_learner(cfg, args.expert, args.expert_weight)
        inputs = run_inputs(args.expert, args.expert_weight)
        if args.init_from is not None:
            # Recorded with the inputs, so --resume refuses a run started from another bundle.
            inputs["init_from"] = init_from_bundle(learner, args.init_from)
        summary = run_training(learner, cfg, args.out, resume=args.resume, progress=not args.quiet,
                               tensorboard=not args.no_tensorboard, overwrite=args.overwrite,
                               inputs=inputs)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"medc-train: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps({k: v for k, v in summary.items() if k != "config"}))
    return 0


def _sweep(args: argparse.Namespace) -> int:
    from ..engines import INTERRUPTED, engine_from_args, run_jobs
    from ..jobs import SUMMARY

    jobs = sweep_jobs(args)
    try:
        run_jobs(jobs, engine_from_args(args), "medc-train")
    except KeyboardInterrupt:
        print(f"medc-train: interrupted; {INTERRUPTED}", file=sys.stderr)
        return 130
    runs = {}
    for job in jobs:
        summary = json.loads((Path(job["out"]) / SUMMARY).read_text())
        runs[job["name"]] = {k: v for k, v in summary.items() if k != "config"}
    print(json.dumps({"runs": runs}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
