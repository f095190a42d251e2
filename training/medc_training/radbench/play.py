"""Playing a benchmark set through the project's evaluator: the world of the episode definitions, the
team of the target-localization core.

:class:`BenchCore` is the batched target-localization core (:class:`~medc_training.envs.
target_localization.TargetLocalization`) with its episodes taken from a set instead of drawn: row i
plays episode i of the chunk it was made with (obstructions, source, starts, S, B). Its readings
follow the benchmark's world (:mod:`medc_training.radbench.scenario`): ``S / d**2 + B`` counts/s
with d in metres (floored at 1 m, which only the source's own cell is nearer), background only where
an obstruction blocks the line of sight, and Poisson counts drawn by inverse CDF from the episode's
count-noise stream (:func:`~medc_training.radbench.scenario.noise_uniforms`, reading t of agent i
from u[t, i]), so an episode's counts do not depend on the batch it is played in or on the policy:
two policies that stand on the same cell at the same step read the same count.

The team is the core's own: its memory, its Bayes estimator and every controller read the readings
under the team's sensor model, :data:`TEAM_SENSING` by default (the ``realistic`` preset with the
strength range of the benchmark, 100-1000 counts/s: the estimator's 1 / (1 + d²) law is within 4% of
the world's 1 / d² beyond 5 m and halves it at 1 m, a model error the team lives with). The core also
records, per episode, the team's first declaration (:func:`medc_training.envs.tl_estimate.declare`)
and its posterior-mean tracking error, the figures :mod:`medc_training.radbench.results` reports.

:func:`play_set` plays a set (or its first episodes) with ``random``, a classical controller
(:data:`medc_training.controllers.CONTROLLERS`), a policy bundle or any policy factory, through
:func:`medc_training.evaluate.play_episodes`, one chunk of episodes per core.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch

from medc_training.envs.target_localization import TargetLocalization
from medc_training.envs.tl_estimate import DEFAULT_THRESHOLD, declare
from medc_training.envs.tl_observation import TeamMemory
from medc_training.envs.tl_sensing import SensingModel, parse_sensing

from .departure import Departure, jittered_positions
from .physics import TEAM_SENSING, episode_tensors, team_sensing, world_rates
from .results import EpisodeResult
from .scenario import noise_uniforms
from .sets import BenchSet

__all__ = ["TEAM_SENSING", "BenchCore", "core_policy", "episode_tensors", "play_set", "poisson_counts",
           "policy_names", "policy_sensing", "resolve_policy", "world_rates"]

#: Observation of the core when a controller plays (they read the team memory, not the observation).
CONTROLLER_OBSERVATION = "maps"


def policy_names() -> tuple[str, ...]:
    """The names :func:`play_set` takes besides a bundle: ``random`` and every classical controller."""
    from medc_training.controllers import CONTROLLERS

    return ("random", *CONTROLLERS)


def poisson_counts(rate: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """float32, the shape of ``rate``: the Poisson count with mean ``rate`` at uniform ``u`` (in (0, 1)),
    by inverse CDF: the smallest k with P(X <= k) = Q(k + 1, rate) >= u (Q the regularised upper
    incomplete gamma), found by bisection in float64. Monotone in the rate for a fixed u."""
    lam = rate.to(torch.float64).clamp(min=1e-12)
    u = u.to(torch.float64)
    lo = torch.full(lam.shape, -1, dtype=torch.int64, device=lam.device)  # P(X <= lo) < u
    hi = (lam + 12.0 * lam.sqrt() + 30.0).ceil().to(torch.int64)  # P(X <= hi) >= u
    while True:
        active = hi - lo > 1
        if not bool(active.any()):
            return hi.to(torch.float32)
        mid = torch.where(active, (lo + hi) // 2, hi)
        ok = torch.special.gammaincc((mid + 1).to(torch.float64), lam) >= u
        hi = torch.where(active & ok, mid, hi)
        lo = torch.where(active & ~ok, mid, lo)


class BenchCore(TargetLocalization):
    """A target-localization core whose row i plays ``episodes[i]`` of ``bench_set`` (module
    docstring). After a row's episode ends the core restarts it (the batched core always runs); only
    the first run of each row is recorded and counted by :func:`play_set`.

    ``sensing``: the team's model (default :data:`TEAM_SENSING`; its success radius is the world's);
    ``observation``: what the team's agents see (a bundle's; the controllers read the memory);
    ``threshold``: the declaration rule's posterior mass; ``run``: which Monte Carlo run of the
    episodes' count noise (0 = the episode's own stream, :func:`~medc_training.radbench.scenario.
    noise_uniforms`); ``departure``: how the world departs from the team's model
    (:class:`~medc_training.radbench.departure.Departure`; None: the nominal world).
    """

    def __init__(self, bench_set: BenchSet, episodes: Sequence[int], *, device: str | torch.device = "cpu",
                 observation: str = CONTROLLER_OBSERVATION, sensing: SensingModel | str | dict | None = None,
                 threshold: float = DEFAULT_THRESHOLD, run: int = 0,
                 departure: Departure | None = None) -> None:
        sensing = TEAM_SENSING if sensing is None else parse_sensing(sensing)
        if sensing.cell_size_m != bench_set.cell_m or sensing.line != "exact" or sensing.attenuation != 0.0:
            raise ValueError("the team's sensing model must have the set's cell size, the exact line of "
                             "sight and obstructions that block it (attenuation 0), as the benchmark's world")
        chosen = [bench_set.episodes[i] for i in episodes]
        if not chosen:
            raise ValueError("BenchCore needs at least one episode")
        super().__init__(num_envs=len(chosen), device=device, seed=0, agents=bench_set.agents, walls=0,
                         grid=bench_set.grid, max_steps=bench_set.max_steps, observation=observation,
                         sensing=sensing, posterior=True, end_on_find=True)
        self.bench_set = bench_set
        self.episode_index = tuple(bench_set.first + int(i) for i in episodes)
        self.threshold = float(threshold)
        # The core checks its own wall count against its layout generator's limit; the set's
        # obstructions are its own (up to 7 rectangles), so the memory keeps a slot for each.
        self.num_walls = bench_set.obstructions
        slots = max(1, bench_set.obstructions)
        self.memory = TeamMemory(self.observation, self.num_envs, self.grid, self.device, self.sensing,
                                 posterior=True, max_walls=slots, rule_out=True)
        self.cell_m = bench_set.cell_m
        self.departure = Departure() if departure is None else departure
        self._defs = episode_tensors(chosen, self.grid, slots, self.device)
        g, dev, k = self.grid, self.device, len(chosen)
        dep = self.departure
        self._defs["strength"] = self._defs["strength"] * dep.strength_scale
        if dep.background is not None:
            self._defs["background"] = torch.full((k,), float(dep.background), device=dev)
        self._defs["transmission"] = torch.full((k,), float(dep.transmission), device=dev)
        self._defs["efficiency"] = torch.full((k,), float(dep.efficiency), device=dev)
        noise = [noise_uniforms(e.noise_seed, self.max_steps, self.num_agents, run) for e in chosen]
        self._noise = torch.from_numpy(np.stack(noise)).to(dev)  # float64 [K, T+1, N]
        # Where readings are taken off the reported cell: a stream of its own per episode and run.
        self._jitter = None
        if dep.position_noise > 0:
            jitter = []
            for e in chosen:
                rng = np.random.default_rng([e.noise_seed, run, 1])
                off = rng.random((self.max_steps + 1, self.num_agents)) < dep.position_noise
                jitter.append(np.where(off, rng.integers(1, 9, off.shape), 0))
            self._jitter = torch.from_numpy(np.stack(jitter)).to(dev)  # int64 [K, T+1, N]
        self._rows = torch.arange(self.num_envs, device=dev)
        idx = torch.arange(g * g, device=dev)
        self._cells = torch.stack((idx // g, idx % g), -1).to(torch.float64)  # [G², 2]
        self._pending: torch.Tensor | None = None
        self._reset_records()

    # -- the episodes and the world's readings ------------------------------------------------
    def _reset_records(self) -> None:
        k, dev = self.num_envs, self.device
        self._first = torch.ones(k, dtype=torch.bool, device=dev)  # the row still plays its first run
        self._length = torch.full((k,), -1, dtype=torch.long, device=dev)
        self._success = torch.zeros(k, dtype=torch.bool, device=dev)
        self._declared_step = torch.full((k,), -1, dtype=torch.long, device=dev)
        self._declared_cell = torch.zeros((k, 2), dtype=torch.long, device=dev)
        self._sq_error = torch.zeros(k, dtype=torch.float64, device=dev)
        self._estimates = torch.zeros(k, dtype=torch.long, device=dev)

    def _take_layouts(self, k: int) -> dict[str, torch.Tensor]:
        rows = self._rows if self._pending is None else self._pending
        lay = {key: value[rows] for key, value in self._defs.items()}
        lay["rows"] = rows
        lay["step"] = torch.zeros(len(rows), dtype=torch.long, device=self.device)
        return lay

    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        self._pending = rows
        super()._start_episodes(rows)
        self._pending = None
        if rows is None:
            self._reset_records()
            none = torch.zeros(self.num_envs, dtype=torch.bool, device=self.device)
            self._track(torch.zeros(self.num_envs, dtype=torch.long, device=self.device), none)
        else:
            self._first[rows] = False

    def _episode_state(self) -> dict[str, torch.Tensor]:
        state = super()._episode_state()
        state["rows"] = self._rows
        state["step"] = self.t + 1
        state["transmission"], state["efficiency"] = self._defs["transmission"], self._defs["efficiency"]
        return state

    def world_rates(self, lay: dict[str, torch.Tensor]) -> torch.Tensor:
        """float32 [K,N]: the world's mean rate (counts/s) at each agent of ``lay``'s rows."""
        return world_rates(self.sensing, self.cell_m, lay)

    def _read(self, lay: dict[str, torch.Tensor]) -> torch.Tensor:
        step = lay["step"].clamp(max=self.max_steps)
        u = self._noise[lay["rows"], step]  # [K,N]
        if self._jitter is not None:
            lay = {**lay, "positions": jittered_positions(lay["positions"], self._jitter[lay["rows"], step],
                                                          lay["walls"])}
        return poisson_counts(self.world_rates(lay), u)

    # -- what the team knows, recorded per episode --------------------------------------------
    def _transition(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        reward, found = super()._transition(actions)
        step = self.t + 1  # this step's readings are reading t + 1 of the episode
        ended = self._first & (found | (step >= self.max_steps))
        self._length[ended] = step[ended]
        self._success[ended] = found[ended]
        # A finding move rules the source's cell out of the estimate (the episode would have ended
        # there), so the estimate after it is not the team's belief: only other rows are tracked.
        self._track(step, found)
        return reward, found

    def _track(self, step: torch.Tensor, found: torch.Tensor) -> None:
        """Fold the team's current estimate into the records of the rows still in their first run
        (and not finding the source this step): squared error of the posterior mean, first
        declaration at ``step`` (int64 [K])."""
        live = self._first & ~found
        if not bool(live.any()):
            return
        p = self.memory.posterior()  # [K, G²]
        mean = (p.to(torch.float64).unsqueeze(-1) * self._cells).sum(1)  # [K, 2] (no BLAS: batch-exact)
        err = mean - self._defs["target"].to(torch.float64)
        self._sq_error += torch.where(live, (err * err).sum(-1) * self.bench_set.cell_m ** 2, 0.0)
        self._estimates += live.long()
        verdict = declare(p, self.grid, self.sensing.success_radius, self.threshold)
        new = live & verdict.declared & (self._declared_step < 0)
        self._declared_step[new] = step[new]
        self._declared_cell[new] = verdict.cell[new]

    def results(self) -> list[EpisodeResult]:
        """Every row's first run, once all have ended (:class:`EpisodeResult`). Raises RuntimeError
        while one still runs."""
        if bool((self._length < 0).any()):
            raise RuntimeError("results() before every episode of the chunk ended; play them to their end")
        out = []
        cell_m = self.bench_set.cell_m
        for row, index in enumerate(self.episode_index):
            step = int(self._declared_step[row])
            error = None
            if step >= 0:
                delta = (self._declared_cell[row] - self._defs["target"][row]).to(torch.float64)
                error = float(delta.norm()) * cell_m
            n = int(self._estimates[row])
            rmse = math.sqrt(float(self._sq_error[row]) / n) if n else None
            out.append(EpisodeResult(self.bench_set.id, index, int(self._length[row]),
                                     bool(self._success[row]), step if step >= 0 else None, error, rmse))
        return out


# ------------------------------------------------------------------------------------------
# playing a set
# ------------------------------------------------------------------------------------------


def _bundle(policy: Any):
    """A loaded PolicyBundle from a bundle or a path, checked for the benchmark (target
    localization, the realistic preset). None when ``policy`` is not a bundle."""
    from medc_training.bundle import PolicyBundle, check_sensing, load_bundle

    if isinstance(policy, PolicyBundle):
        bundle = policy
    elif isinstance(policy, str) and "+" in policy and policy not in policy_names():
        from medc_training.bundle.ensemble import load_ensemble

        members = policy.split("+")
        missing = [m for m in members if not Path(m).is_file()]
        if missing:
            raise ValueError(f"ensemble {policy[:80]!r}: no bundle at {missing[0][:80]!r} (an ensemble is "
                             "bundle paths joined by '+')")
        bundle = load_ensemble(members)
    elif isinstance(policy, (str, Path)) and str(policy) not in policy_names():
        if not Path(policy).is_file():
            raise ValueError(f"unknown policy {str(policy)[:80]!r}: give one of {', '.join(policy_names())} "
                             "or the path of a policy bundle (.safetensors)")
        bundle = load_bundle(policy)
    else:
        return None
    if bundle.application != BenchCore.name:
        raise ValueError(f"the benchmark plays {BenchCore.name}; this bundle is for {bundle.application!r}")
    check_sensing(bundle.manifest, policy_sensing(bundle), "the bundle")
    return bundle


def policy_sensing(bundle: Any = None, sensing: SensingModel | str | dict | None = None) -> SensingModel:
    """The team's model a policy plays under: ``sensing`` when given (a bundle trained under another
    background prior is refused), else the bundle's own (:data:`TEAM_SENSING` with the background
    prior its manifest records, if any), else :data:`TEAM_SENSING`. ``bundle``: as
    :func:`resolve_policy` gave it (None: a controller or a factory)."""
    from medc_training.bundle import check_sensing, manifest_prior

    if sensing is not None:
        model = TEAM_SENSING if sensing == TEAM_SENSING.name else parse_sensing(sensing)
        if bundle is not None:
            check_sensing(bundle.manifest, model, "the bundle")
        return model
    return TEAM_SENSING if bundle is None else team_sensing(manifest_prior(bundle.manifest))


def resolve_policy(policy: Any) -> tuple[Any, str]:
    """(the loaded bundle or None, the observation the core must make) for ``policy`` as
    :func:`play_set` takes it. Raises ValueError for an unknown name or an unusable bundle."""
    bundle = _bundle(policy)
    if bundle is not None:
        observation = bundle.observation or "maps"
    else:  # a factory may name the observation its policy reads (an attribute ``observation``)
        observation = getattr(policy, "observation", None) if callable(policy) else None
        observation = observation or CONTROLLER_OBSERVATION
    if bundle is None and not callable(policy) and policy not in policy_names():
        raise ValueError(f"unknown policy {str(policy)[:80]!r}: give one of {', '.join(policy_names())}, "
                         "a policy bundle or a factory")
    return bundle, observation


def core_policy(core: BenchCore, policy: Any, bundle: Any = None):
    """The evaluator's Policy for ``policy`` on ``core`` (None: random moves); ``bundle`` as
    :func:`resolve_policy` gave it."""
    from medc_training.controllers import CONTROLLERS, controller_policy
    from medc_training.evaluate import net_policy

    if bundle is not None:
        if tuple(bundle.obs_shape) != tuple(core.obs_shape):
            raise ValueError(f"the bundle takes observations of shape {tuple(bundle.obs_shape)}, but "
                             f"{core.observation_name!r} on a {core.grid}x{core.grid} grid is "
                             f"{tuple(core.obs_shape)}")
        return net_policy(bundle.net, bundle.device)
    if callable(policy):
        return policy(core)
    if policy in CONTROLLERS:
        return controller_policy(policy, core)
    return None


def _tempered(policy, temperature: float):
    def logits(obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        return policy(obs, mask) / temperature

    return logits


def play_set(bench_set: BenchSet, policy: Any = "greedy", *, episodes: int | None = None, batch: int = 100,
             device: str | torch.device = "cpu", sensing: SensingModel | str | dict | None = None,
             threshold: float = DEFAULT_THRESHOLD, seed: int = 12345, run: int = 0,
             progress: Callable[[int], None] | None = None, departure: Departure | None = None,
             temperature: float = 0.0) -> list[EpisodeResult]:
    """Play the first ``episodes`` episodes of ``bench_set`` (all when None), each to its end, with
    ``policy``, ``batch`` episodes at a time; return their results in episode order.

    ``policy``: ``random`` (uniformly random valid moves), a controller's name
    (:data:`medc_training.controllers.CONTROLLERS`), a PolicyBundle or a bundle's path (played greedily
    on the observation it was trained on), or a callable ``factory(core) -> Policy`` (a
    :data:`medc_training.evaluate.Policy` for that core; the core makes the observation named by the
    factory's ``observation`` attribute where it has one). ``seed`` seeds the random policy's draws;
    ``run`` picks the Monte Carlo run of the count noise (0: each episode's own stream);
    ``sensing``: the team's model (:func:`policy_sensing`; None: a bundle plays under the background
    prior it was trained with, a controller or a factory under :data:`TEAM_SENSING`);
    ``departure`` how the world departs from the team's model (None: nominal); ``temperature`` > 0:
    a bundle samples its move from softmax(logits / temperature) with a stream seeded by ``seed``
    instead of taking the most probable one (controllers are unaffected). ``progress(n)`` is called
    after each chunk with the episodes it played.
    """
    from medc_training.evaluate import play_episodes

    count = len(bench_set.episodes) if episodes is None else min(int(episodes), len(bench_set.episodes))
    if count < 1 or batch < 1:
        raise ValueError("play_set needs at least one episode and a batch of at least one")
    bundle, observation = resolve_policy(policy)
    if isinstance(temperature, bool) or not isinstance(temperature, int | float) \
            or not 0.0 <= temperature <= 100.0:
        raise ValueError("temperature must be a number in [0, 100] (0: the most probable move), "
                         f"got {temperature!r}")
    sampled = bundle is not None and temperature > 0.0
    sensing = policy_sensing(bundle, sensing)
    out: list[EpisodeResult] = []
    for lo in range(0, count, batch):
        chunk = list(range(lo, min(count, lo + batch)))
        core = BenchCore(bench_set, chunk, device=device, observation=observation, sensing=sensing,
                         threshold=threshold, run=run, departure=departure)
        chosen = core_policy(core, policy, bundle)
        if sampled:
            chosen = _tempered(chosen, temperature)
        played = play_episodes(core, chosen, episodes=len(chunk), seed=seed, greedy=not sampled)
        results = core.results()
        for r, length, success in zip(results, played.lengths, played.successes):
            if (r.length, r.success) != (length, success):
                raise RuntimeError(f"episode {r.index} of {bench_set.id}: the core recorded "
                                   f"{(r.length, r.success)}, the evaluator {(length, success)}")
        out.extend(results)
        if progress is not None:
            progress(len(chunk))
    return out
