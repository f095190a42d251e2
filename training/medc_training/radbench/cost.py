"""What one decision costs, measured the same way for every policy (``medc-radbench --cost``).

RAD-A2C's case for a learned searcher over its particle-filter controller is the computation per
action; this module measures it here, on the benchmark's own episodes, in one process and one torch
thread:

* **the batched evaluator** (B episodes at once, every agent of each): milliseconds per call and
  decisions (one agent's move) per second, at B = 1 and at a large batch;
* **an agent node's decision** (B = 1): the work ``medc-agent`` does per step for the team's last
  agent, which is the most for a coordinated searcher (it computes its teammates' choices before
  its own); for a bundle, building that agent's observation from the team memory and its greedy
  move from the network in the node's runtime (:mod:`medc_training.bundle.runtime`: ``auto``
  takes onnxruntime where it agrees with PyTorch, as the agent nodes do). DDS transport is not in
  it (``medc-bench ros`` measures the graph: a few milliseconds);
* **the work per decision**: for the information-driven searchers the likelihood terms evaluated
  (hypothesis x count value x candidate move, :data:`medc_training.searchers.STATS`), for a bundle
  its network's multiply-accumulates (``torch.utils.flop_counter``: convolutions and linear layers).

Each figure is over the first steps of the episodes (the first call, which builds kernels and
tables, is not counted): the posterior is broadest there, so an information-driven searcher's
decisions are at their dearest.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from collections.abc import Sequence
from types import SimpleNamespace
from typing import Any

import torch

from ..stats import percentile
from .play import BenchCore, core_policy, policy_sensing, resolve_policy
from .sets import BenchSet

__all__ = ["decision_cost", "runtime_agreement"]


def _node_call(policy: Any, bundle: Any, core: BenchCore, runtime: str = "auto",
               endgame: float | None = None):
    """A callable doing one agent node's decision work on ``core`` (B = 1) for its last agent, a
    bundle's network run in ``runtime`` (:mod:`medc_training.bundle.runtime`), or, with ``endgame``
    (a tau), a shortest path towards the posterior's mode once it holds tau of the mass and the agent
    can reach its success region (:func:`~medc_training.radbench.endgame.agent_move`, the agent
    nodes' own decision); the callable returns whether it planned. None for random moves."""
    from medc_training.controllers import CONTROLLERS, COORDINATED, controller_scores

    n = core.num_agents
    if bundle is not None:
        from medc_training.bundle.runtime import decider

        from .endgame import agent_move

        runner = decider(bundle, runtime)

        def forward(obs: torch.Tensor, mask: torch.Tensor) -> bool:
            # The node's steps: with an endgame, whether the posterior the step left holds tau on its
            # mode, and if so this agent's shortest-path move; else the agent's observation from the
            # team memory (its source maps from that posterior; the agent's own window), then its
            # greedy move from the network in the node's runtime.
            with torch.no_grad():
                if endgame is not None and agent_move(core.memory.posterior(), core.walls, core.positions,
                                                      core.sensing, endgame, n - 1,
                                                      core.mask[0, n - 1]) is not None:
                    return True
                view = core.memory.observe_agent(core.positions, core.walls, n - 1)
                runner.act(view, core.mask[:, n - 1])
            return False

        forward.runtime = runner.runtime
        return forward
    if isinstance(policy, str) and policy in CONTROLLERS:
        rows = slice(0, n) if policy in COORDINATED else slice(n - 1, n)

        def decide(obs: torch.Tensor, mask: torch.Tensor) -> bool:
            view = SimpleNamespace(memory=core.memory, positions=core.positions[:, rows], walls=core.walls,
                                   mask=core.mask[:, rows], noise=core.noise, name=core.name,
                                   observation_name=core.observation_name)
            with torch.no_grad():
                controller_scores(policy, view)
            return False

        return decide
    return None


def _macs(bundle: Any, obs: torch.Tensor) -> float | None:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter, torch.no_grad():
        bundle.net(obs[:1])
    return counter.get_total_flops() / 2.0  # a multiply-accumulate is two flops


def decision_cost(bench_set: BenchSet, policy: Any, *, batch: int, steps: int = 5,
                  node_steps: int = 20, runtime: str = "auto", sensing: Any = None,
                  endgame: float | None = None) -> dict[str, Any]:
    """Cost figures of ``policy`` (a name or a bundle, as :func:`~medc_training.radbench.play.play_set`
    takes it) on the first episodes of ``bench_set`` (module docstring): ``steps`` timed calls of the
    batched evaluator at B = ``batch`` (episodes repeated when the set has fewer), ``node_steps`` at
    B = 1, each after one untimed call; an agent node's decision with a bundle's network in ``runtime``
    (``node_runtime``: the one it ran in). ``sensing``: the team's model
    (:func:`~medc_training.radbench.play.policy_sensing`); ``endgame``: a bundle's node decision plans
    with the classical endgame at this tau (``endgame_decisions``: the node decisions it planned,
    ``endgame_ms_p50/p99`` their cost; the batched figures are the network's alone)."""
    from medc_training import searchers

    from .endgame import check_tau

    bundle, observation = resolve_policy(policy)
    if endgame is not None and bundle is not None:
        check_tau(endgame)
    out: dict[str, Any] = {"batch": batch, "agents": bench_set.agents, "grid": bench_set.grid}
    for label, b, count in (("b1", 1, node_steps), (f"b{batch}", batch, steps)):
        idx = [i % len(bench_set.episodes) for i in range(b)]
        core = BenchCore(bench_set, idx, observation=observation, sensing=policy_sensing(bundle, sensing))
        chosen = core_policy(core, policy, bundle)
        node = _node_call(policy, bundle, core, runtime, endgame) if b == 1 else None
        gen = torch.Generator().manual_seed(0)
        obs, mask = core.reset()
        calls, nodes, terms, plans = [], [], [], []
        for t in range(count + 1):
            flat_obs, flat_mask = obs.flatten(0, 1), mask.flatten(0, 1)
            searchers.STATS["likelihood_terms"] = 0
            start = time.perf_counter()
            if chosen is None:
                logits = torch.rand(flat_mask.shape, generator=gen)
            else:
                logits = chosen(flat_obs, flat_mask)
            took = time.perf_counter() - start
            work = searchers.STATS["likelihood_terms"]
            if node is not None:
                start = time.perf_counter()
                planned = node(flat_obs, flat_mask)
                node_took = time.perf_counter() - start
            if t > 0:
                calls.append(took)
                terms.append(work)
                if node is not None:
                    nodes.append(node_took)
                    if planned:
                        plans.append(node_took)
            actions = logits.view(mask.shape).masked_fill(~mask, -math.inf).argmax(-1)
            step = core.step(actions)
            obs, mask = step.obs, step.mask
        decisions = b * core.num_agents
        out[label] = {
            "call_ms_p50": round(1000 * percentile(calls, 50), 3),
            "call_ms_p99": round(1000 * percentile(calls, 99), 3),
            "decisions_per_s": round(decisions * len(calls) / max(sum(calls), 1e-9), 1),
        }
        if b == 1:
            work = statistics.fmean(terms) / decisions
            out["likelihood_terms_per_decision"] = round(work)
            if nodes:
                out["node_ms_p50"] = round(1000 * percentile(nodes, 50), 3)
                out["node_ms_p99"] = round(1000 * percentile(nodes, 99), 3)
                if bundle is not None:
                    out["node_runtime"] = node.runtime
                if endgame is not None and bundle is not None:
                    out["endgame_decisions"] = len(plans)
                    if plans:
                        out["endgame_ms_p50"] = round(1000 * percentile(plans, 50), 3)
                        out["endgame_ms_p99"] = round(1000 * percentile(plans, 99), 3)
            if bundle is not None:
                out["macs_per_decision"] = _macs(bundle, flat_obs)
    return out


def runtime_agreement(sets: Sequence[BenchSet], policy: Any, *, batch: int = 200,
                      runtime: str = "onnxruntime") -> dict[str, Any]:
    """How often an agent node running ``policy``'s network in ``runtime`` would choose another
    greedy move than PyTorch on the episodes of ``sets``, played to their end with PyTorch's moves
    (each decision of each agent while its episode runs counted once): ``decisions``, ``differ``
    (how many chose otherwise), ``share`` and the largest logit difference seen (``max_logit_gap``)."""
    from medc_training.bundle.policy import allowed_logits
    from medc_training.bundle.runtime import decider

    bundle, observation = resolve_policy(policy)
    if bundle is None:
        raise ValueError("runtime agreement is measured for a bundle, not a controller")
    other, reference = decider(bundle, runtime), decider(bundle, "torch")
    decisions = differ = 0
    gap = 0.0
    for bench_set in sets:
        for start in range(0, len(bench_set.episodes), batch):
            rows = list(range(start, min(start + batch, len(bench_set.episodes))))
            core = BenchCore(bench_set, rows, observation=observation, sensing=policy_sensing(bundle))
            obs, mask = core.reset()
            live = torch.ones(len(rows), dtype=torch.bool)
            while bool(live.any()):
                flat_obs, flat_mask = obs.flatten(0, 1), mask.flatten(0, 1)
                want_logits, got_logits = reference.heads(flat_obs)[0], other.heads(flat_obs)[0]
                want = allowed_logits(want_logits, flat_mask).argmax(-1).view(mask.shape[:2])
                got = allowed_logits(got_logits, flat_mask).argmax(-1).view(mask.shape[:2])
                counted = live.unsqueeze(1).expand_as(want)
                decisions += int(counted.sum())
                differ += int(((want != got) & counted).sum())
                gap = max(gap, float((want_logits - got_logits).abs().max()))
                step = core.step(want)
                live &= ~step.done
                obs, mask = step.obs, step.mask
    return {"runtime": other.runtime, "decisions": decisions, "differ": differ,
            "share": differ / max(decisions, 1), "max_logit_gap": gap}


def main(argv: list[str] | None = None) -> int:
    """``python -m medc_training.radbench.cost --agreement BUNDLE``: :func:`runtime_agreement` on a
    set file (the frozen one of ``--grid``/``--agents``, or ``--sets-file``)."""
    from .sets import SetFileError, add_set_arguments, sets_from_args

    p = argparse.ArgumentParser(prog="python -m medc_training.radbench.cost",
                                description="How often an agent node's runtime chooses another greedy "
                                            "move than PyTorch on the benchmark's episodes")
    p.add_argument("--agreement", required=True, metavar="BUNDLE", help="the policy bundle")
    p.add_argument("--runtime", default="onnxruntime", choices=("onnxruntime", "torch"),
                   help="the runtime compared with PyTorch (default onnxruntime)")
    add_set_arguments(p)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    try:
        sets = sets_from_args(args)
        found = runtime_agreement(sets, args.agreement, runtime=args.runtime)
    except (SetFileError, ValueError, OSError) as exc:
        print(f"medc_training.radbench.cost: {exc}", file=sys.stderr)
        return 2
    print(f"{found['runtime']} against PyTorch on {sum(len(s.episodes) for s in sets)} episodes: "
          f"{found['differ']} of {found['decisions']:,} greedy moves differ ({100 * found['share']:.4f}%), "
          f"largest logit difference {found['max_logit_gap']:.2g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
