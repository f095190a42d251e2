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

import math
import statistics
import time
from types import SimpleNamespace
from typing import Any

import torch

from ..stats import percentile
from .play import BenchCore, core_policy, resolve_policy
from .sets import BenchSet

__all__ = ["decision_cost"]


def _node_call(policy: Any, bundle: Any, core: BenchCore, runtime: str = "auto"):
    """A callable doing one agent node's decision work on ``core`` (B = 1) for its last agent, a
    bundle's network run in ``runtime`` (:mod:`medc_training.bundle.runtime`); None for random
    moves."""
    from medc_training.controllers import CONTROLLERS, COORDINATED, controller_scores

    n = core.num_agents
    if bundle is not None:
        from medc_training.bundle.runtime import decider

        runner = decider(bundle, runtime)

        def forward(obs: torch.Tensor, mask: torch.Tensor) -> None:
            # The node's two steps: the agent's observation from the team memory (its source maps
            # from the posterior the step left, as a searcher's scores are; the agent's own window),
            # then its greedy move from the network in the node's runtime.
            with torch.no_grad():
                view = core.memory.observe_agent(core.positions, core.walls, n - 1)
                runner.act(view, core.mask[:, n - 1])

        forward.runtime = runner.runtime
        return forward
    if isinstance(policy, str) and policy in CONTROLLERS:
        rows = slice(0, n) if policy in COORDINATED else slice(n - 1, n)

        def decide(obs: torch.Tensor, mask: torch.Tensor) -> None:
            view = SimpleNamespace(memory=core.memory, positions=core.positions[:, rows], walls=core.walls,
                                   mask=core.mask[:, rows], noise=core.noise, name=core.name,
                                   observation_name=core.observation_name)
            with torch.no_grad():
                controller_scores(policy, view)

        return decide
    return None


def _macs(bundle: Any, obs: torch.Tensor) -> float | None:
    from torch.utils.flop_counter import FlopCounterMode

    with FlopCounterMode(display=False) as counter, torch.no_grad():
        bundle.net(obs[:1])
    return counter.get_total_flops() / 2.0  # a multiply-accumulate is two flops


def decision_cost(bench_set: BenchSet, policy: Any, *, batch: int, steps: int = 5,
                  node_steps: int = 20, runtime: str = "auto") -> dict[str, Any]:
    """Cost figures of ``policy`` (a name or a bundle, as :func:`~medc_training.radbench.play.play_set`
    takes it) on the first episodes of ``bench_set`` (module docstring): ``steps`` timed calls of the
    batched evaluator at B = ``batch`` (episodes repeated when the set has fewer), ``node_steps`` at
    B = 1, each after one untimed call; an agent node's decision with a bundle's network in ``runtime``
    (``node_runtime``: the one it ran in)."""
    from medc_training import searchers

    bundle, observation = resolve_policy(policy)
    out: dict[str, Any] = {"batch": batch, "agents": bench_set.agents, "grid": bench_set.grid}
    for label, b, count in (("b1", 1, node_steps), (f"b{batch}", batch, steps)):
        idx = [i % len(bench_set.episodes) for i in range(b)]
        core = BenchCore(bench_set, idx, observation=observation)
        chosen = core_policy(core, policy, bundle)
        node = _node_call(policy, bundle, core, runtime) if b == 1 else None
        gen = torch.Generator().manual_seed(0)
        obs, mask = core.reset()
        calls, nodes, terms = [], [], []
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
                node(flat_obs, flat_mask)
                node_took = time.perf_counter() - start
            if t > 0:
                calls.append(took)
                terms.append(work)
                if node is not None:
                    nodes.append(node_took)
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
            if bundle is not None:
                out["macs_per_decision"] = _macs(bundle, flat_obs)
    return out
