"""How well the team's declaration says where the source is (:mod:`medc_training.envs.tl_estimate`).

Plays fixed, seeded episodes of a batched target-localization core (the episodes
:func:`medc_training.evaluate.play_episodes` plays: round r resets with ``round_seed(seed, r)``,
each environment's first episode counts) and checks the declaration rule on the team's posterior
after every step (step 0 included: the first readings), as the ROS agents do. Two end rules, as the
simulator's ``end_on`` parameter:

``either``
    the episode ends when an agent finds the source (the core's own rule, as in training) or at
    the team's first declaration, whichever comes first (or at max_steps);
``declaration``
    finding the source does not end the episode (a real driver cannot know it): the core is made
    with ``end_on_find=False``, so the team's estimate no longer rules out the cells it has stood
    on, and only the declaration or max_steps ends it.

Per episode: how it ended, its length (moves applied), and for a declaration the distance in
cells from the declared cell to the true source and whether a UAV on that cell would find it (the
preset's success radius). ``python -m medc_training.cli.declaration_accuracy BUNDLE_OR_CONTROLLER ...``
prints one JSON line per configuration.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

import torch

from .envs.tl_estimate import DEFAULT_THRESHOLD, check_rule, declare
from .evaluate import round_seed

#: The end rules of the simulator (``end_on``) a declaration study can play.
END_RULES = ("either", "declaration")


@torch.no_grad()
def declaration_episodes(env, policy: Callable | None, *, episodes: int, seed: int = 12345,
                         radius: float | None = None, threshold: float = DEFAULT_THRESHOLD) -> list[dict]:
    """Play ``episodes`` fixed episodes of ``env`` (made with ``posterior=True``, or with an
    observation that shows the estimate) greedily with ``policy`` (logits [M, A] for observations
    and masks, as :mod:`medc_training.evaluate` takes; None = uniformly random valid moves) and
    return one dict per episode: ``ended_by`` (``declaration``, ``source`` or ``max_steps``),
    ``length``, ``declared_step``, ``error`` (cells from the declared cell to the source),
    ``correct`` (error within the preset's success radius), ``mass``.

    ``radius`` None = the sensing preset's success radius. The core's ``end_on_find`` decides the
    rule: True = ``either``, False = ``declaration`` (module docstring).
    """
    rows = []
    for row in threshold_episodes(env, policy, episodes=episodes, seed=seed, radius=radius,
                                  thresholds=(threshold,)):
        first = row["declarations"][0]
        if first is None:
            rows.append({"ended_by": row["ended_by"], "length": row["length"], "declared_step": None,
                         "error": None, "correct": None, "mass": None})
        else:
            rows.append({"ended_by": "declaration", "length": first["step"], "declared_step": first["step"],
                         "error": first["error"], "correct": first["correct"], "mass": first["mass"]})
    return rows


@torch.no_grad()
def threshold_episodes(env, policy: Callable | None, *, episodes: int, seed: int = 12345,
                       radius: float | None = None, thresholds: tuple[float, ...] = (DEFAULT_THRESHOLD,),
                       step_masses: list | None = None) -> list[dict]:
    """The declarations several thresholds make on the same fixed episodes, in one play.

    The episodes, the play and the rule are :func:`declaration_episodes`'; the moves do not depend
    on the rule, so the declaration a threshold makes is the first step its rule holds, provided the
    core has not ended the episode before. An episode is played until the core ends it or the
    highest threshold declares. One dict per episode: ``ended_by`` (``declaration`` when the highest
    threshold declared, else ``source`` or ``max_steps``), ``length`` (moves played), ``strength``
    and ``background`` (the episode's, None when the team knows them), and ``declarations``: per
    threshold, in the order given, None or ``{"step", "mass", "error", "correct"}``.

    ``step_masses``, when given, receives per step a pair (mass float32 [R], right bool [R]) for the
    R episodes still running: the rule's mass at the MAP cell and whether the source lies within
    the radius of it (every step's verdict, not only the declarations).
    """
    from .evaluate import _choose, _generator, net_policy

    if policy is not None and hasattr(policy, "net"):
        policy = net_policy(policy.net, policy.device)
    if env.memory.log_post is None:
        raise ValueError("the core keeps no source posterior: make it with posterior=True")
    if not thresholds:
        raise ValueError("threshold_episodes needs at least one threshold")
    radius = env.sensing.success_radius if radius is None else radius
    for threshold in thresholds:
        radius, _ = check_rule(radius, threshold)
    b = env.num_envs
    gen = _generator(env, seed, "multinomial")
    out: list[dict] = []
    for r in range(math.ceil(episodes / b)):
        wanted = min(b, episodes - r * b)
        obs, mask = env.reset(seed=round_seed(seed, r))
        target = torch.tensor([env.state(i).target for i in range(b)])
        strength = getattr(env, "strength", None)
        rows = [{"ended_by": None, "length": None, "declarations": [None] * len(thresholds),
                 "strength": None if strength is None else float(strength[i]),
                 "background": None if strength is None else float(env.background[i])} for i in range(b)]
        ended = torch.zeros(b, dtype=torch.bool)

        running = _declare_running(env, rows, ended, target, radius, thresholds)  # step 0: the first readings
        if step_masses is not None:
            step_masses.append(running)
        for _ in range(env.max_steps):
            if bool(ended[:wanted].all()):
                break
            step_out = env.step(_choose(env, policy, obs, mask, True, "multinomial", gen))
            done = (step_out.terminated | step_out.truncated).cpu() & ~ended
            for i in done.nonzero().flatten().tolist():
                rows[i]["ended_by"] = "source" if bool(step_out.success[i]) else "max_steps"
                rows[i]["length"] = int(step_out.episode_length[i])
            # Rows that just ended were reset by the core (their posterior is the next episode's).
            ended |= done
            running = _declare_running(env, rows, ended, target, radius, thresholds)
            if step_masses is not None:
                step_masses.append(running)
            obs, mask = step_out.obs, step_out.mask
        missing = [i for i in range(wanted) if rows[i]["ended_by"] is None]
        if missing:
            raise RuntimeError(f"episodes {missing} of round {r} neither ended nor declared in max_steps")
        out.extend(rows[:wanted])
    return out


def _declare_running(env, rows: list, ended: torch.Tensor, target: torch.Tensor, radius: float,
                     thresholds: tuple[float, ...]) -> tuple[torch.Tensor, torch.Tensor]:
    """Record, for each running episode (not ``ended``) and each threshold that has not declared in
    it yet, a declaration when the posterior passes that threshold's rule now (this step's readings
    in); an episode whose highest threshold has declared is marked ended. Returns this step's (mass,
    right) of the running episodes."""
    verdict = declare(env.memory.posterior().cpu(), env.grid, radius, min(thresholds))
    error = torch.linalg.vector_norm((verdict.cell - target).float(), dim=1)
    right = error <= env.sensing.success_radius + 1e-9
    passes = [verdict.mass >= threshold for threshold in thresholds]  # as declare() compares
    running = ~ended
    step = None
    for i in (verdict.declared & running).nonzero().flatten().tolist():
        step = env.state(i).step if step is None else step  # every running episode is on the same step
        marks = rows[i]["declarations"]
        for k, passed in enumerate(passes):
            if marks[k] is None and bool(passed[i]):
                marks[k] = {"step": step, "mass": float(verdict.mass[i]), "error": float(error[i]),
                            "correct": bool(right[i])}
        if all(mark is not None for mark in marks):
            rows[i]["ended_by"], rows[i]["length"] = "declaration", step
            ended[i] = True
    return verdict.mass[running], right[running]


def summarize(rows: list[dict]) -> dict:
    """Counts and means of :func:`declaration_episodes`' rows."""
    n = len(rows)
    declared = [row for row in rows if row["ended_by"] == "declaration"]
    errors = sorted(row["error"] for row in declared)
    steps = [row["declared_step"] for row in declared]
    return {
        "episodes": n,
        "declared": len(declared),
        "declared_correct": sum(1 for row in declared if row["correct"]),
        "found_first": sum(1 for row in rows if row["ended_by"] == "source"),
        "ended_at_max_steps": sum(1 for row in rows if row["ended_by"] == "max_steps"),
        "mean_error_cells": sum(errors) / len(errors) if errors else None,
        "max_error_cells": errors[-1] if errors else None,
        "mean_declared_step": sum(steps) / len(steps) if steps else None,
        "mean_length": sum(row["length"] for row in rows) / n if n else None,
    }


def add_episode_arguments(p: argparse.ArgumentParser, episodes: int) -> None:
    """The command-line arguments of a declaration study's episodes and team (this module's and
    :mod:`medc_lab.studies.calibration`'s): the policy, the episodes, the end rules, the radius and the
    scenario of a classical team (a bundle brings its own)."""
    from .controllers import CONTROLLERS

    p.add_argument("policy", help="a policy bundle, 'random' (uniformly random valid moves) or a classical "
                                  f"controller's name ({', '.join(CONTROLLERS)})")
    p.add_argument("--episodes", type=int, default=episodes)
    p.add_argument("--envs", type=int, default=32)
    p.add_argument("--seed", type=int, default=12345)
    p.add_argument("--rule", choices=END_RULES, action="append", help="end rule(s) (default: both)")
    p.add_argument("--radius", type=float, default=None, help="cells (default: the preset's success radius)")
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--walls", type=int, default=2)
    p.add_argument("--grid", type=int, default=20)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--sensing", default="realistic")


def study_team(args: argparse.Namespace) -> tuple[object | None, dict]:
    """(bundle or None, environment options) for :func:`add_episode_arguments`' arguments: a bundle's
    own scenario (and observation), or the arguments' for a classical team or random moves."""
    from .bundle import load_bundle
    from .controllers import CONTROLLERS

    if args.policy in (*CONTROLLERS, "random"):
        return None, {"agents": args.agents, "walls": args.walls, "grid": args.grid,
                      "max_steps": args.max_steps, "sensing": args.sensing}
    bundle = load_bundle(args.policy)
    attrs = dict(bundle.manifest.get("environment", {}))
    if bundle.observation is not None:
        attrs["observation"] = bundle.observation
    return bundle, attrs


def study_policy(name: str, bundle, env):
    """The team that plays a study on ``env``: the bundle, None (random moves) or the controller."""
    from .controllers import controller_policy

    if bundle is not None:
        return bundle
    return None if name == "random" else controller_policy(name, env)
