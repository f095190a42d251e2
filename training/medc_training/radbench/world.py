"""The benchmark's world as a training environment: fresh RAD-A2C episodes, never the frozen sets.

:class:`BenchWorld` is the batched target-localization core whose episodes come from the benchmark's
own generator (:func:`~medc_training.radbench.scenario.generate_set`: obstructions of 2-5 m, sources
at least 10 m from every start, strength and background matched to RAD-A2C's SNR bins) and whose
readings follow the benchmark's world (``S / d**2 + B`` counts/s, background only where an
obstruction blocks the line of sight, Poisson counts), exactly as :class:`~medc_training.radbench.
play.BenchCore` plays a frozen set. The team (memory, Bayes estimator, observations, experts that
read it) uses the team's sensor model, :data:`~medc_training.radbench.play.TEAM_SENSING` by default.

Where they differ: a training world draws its episodes from seeds far from the frozen sets' (the
sets use seed 2021; a world draws from ``TRAIN_SEED_BASE`` plus a number taken from the core's
generator, so ``reset(seed)`` replays the same episodes), mixes every obstruction count from 0 to
``walls`` and the three SNR bins in equal shares, draws its count noise from the core's generator
instead of the episode's stream, and records nothing per episode.

**Domain randomisation.** A training world can depart from the team's model episode by episode, so a
team learns to cope where a model-based searcher would not (the departures of :mod:`~medc_training.
radbench.departure`, each drawn per episode): ``transmission_max`` (obstructions let a fraction
uniform in [0, max] through), ``efficiency_spread`` (detector efficiency uniform in [1 - s, 1 + s]),
``strength_spread`` (strength times a factor log-uniform in [1/s, s]), ``background_low`` /
``background_high`` (background uniform in that range instead of the episode's own, both given or
neither), ``position_noise_max`` (each reading one cell off the reported position with a probability
uniform in [0, max]). The non-default ones are in :attr:`BenchWorld.attributes`, hence in the
manifest of every bundle trained there.

Build it through the registry of cores, so that a training config, a bundle's manifest and the
evaluator name it: ``make_batched(TARGET_LOCALIZATION, world="radbench", grid=20, agents=3,
walls=7, max_steps=120, sensing="realistic")`` (``medc-train --world radbench``).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch

from medc_training.envs.target_localization import TargetLocalization
from medc_training.envs.tl_observation import DEFAULT_OBSERVATION, TeamMemory
from medc_training.envs.tl_sensing import SensingModel, parse_sensing

from .departure import jittered_positions
from .physics import PRIOR_OPTIONS, TEAM_SENSING, background_prior, episode_tensors, team_sensing, world_rates
from .scenario import GRIDS, MAX_STEPS, OBSTRUCTION_COUNTS, generate_set

__all__ = ["OFF_NOMINAL_OPTIONS", "RANDOMISATION_OPTIONS", "SNR_MIX", "TRAIN_SEED_BASE", "WORLD",
           "BenchWorld", "draw_episodes"]

#: The name a config, a manifest and ``make_batched(..., world=...)`` give this world.
WORLD = "radbench"
#: Training worlds draw episodes from seeds at and above this (the frozen sets use 2021).
TRAIN_SEED_BASE = 1_000_000_000
#: The SNR bins a training world mixes, in equal shares (those of the frozen sets).
SNR_MIX: tuple[str, ...] = ("low", "medium", "high")
#: Each numeric randomisation option (module docstring): (its value without randomisation, lowest,
#: highest).
_SPREADS: dict[str, tuple[float, float, float]] = {
    "transmission_max": (0.0, 0.0, 1.0), "efficiency_spread": (0.0, 0.0, 0.9),
    "strength_spread": (1.0, 1.0, 10.0), "position_noise_max": (0.0, 0.0, 1.0)}
#: The background range (counts/s), given both or neither.
_BACKGROUND: tuple[str, str] = ("background_low", "background_high")
#: The domain-randomisation options, as :attr:`BenchWorld.attributes` (hence a bundle's manifest)
#: names them.
RANDOMISATION_OPTIONS: tuple[str, ...] = (*_SPREADS, *_BACKGROUND)
#: The attributes by which a training world's episodes depart from the nominal world's: the
#: randomisation options, ``walls_min`` (the harder obstruction counts only) and ``snr_max`` (the
#: weaker SNR bins only). A bundle whose manifest names any of them is refused where it would run at
#: the nominal model (``medc_training.bundle.check_world``).
OFF_NOMINAL_OPTIONS: tuple[str, ...] = (*RANDOMISATION_OPTIONS, "walls_min", "snr_max")


def draw_episodes(grid: int, agents: int, max_obstructions: int, count: int, seed: int,
                  min_obstructions: int = 0, snr_max: int = len(SNR_MIX) - 1):
    """About ``count`` fresh benchmark episodes (list of :class:`~medc_training.radbench.scenario.
    Episode`), an equal share for every obstruction count ``min_obstructions``..``max_obstructions``
    and SNR bin of :data:`SNR_MIX` up to index ``snr_max`` (all three by default), shuffled; the same
    arguments give the same episodes. The last few draws are kept: a training run's evaluation draws
    the same pool at every evaluation."""
    return list(_draw_episodes(grid, agents, max_obstructions, count, seed, min_obstructions, snr_max))


@functools.lru_cache(maxsize=4)
def _draw_episodes(grid: int, agents: int, max_obstructions: int, count: int, seed: int,
                   min_obstructions: int, snr_max: int) -> tuple:
    groups = [(o, name) for o in range(min_obstructions, max_obstructions + 1)
              for name in SNR_MIX[:snr_max + 1]]
    per = max(1, -(-count // len(groups)))
    episodes = []
    for o, name in groups:
        drawn, _ = generate_set(grid, agents, o, name, per, seed=seed)
        episodes.extend(drawn)
    order = np.random.default_rng(seed).permutation(len(episodes))
    return tuple(episodes[i] for i in order)


class BenchWorld(TargetLocalization):
    """Target localization in the benchmark's world, on fresh episodes (module docstring).

    ``walls``: the most obstructions an episode has (0..7; every count from ``walls_min``, 0 by
    default, up to it in equal shares: ``walls_min`` > 0 trains on the harder counts only);
    ``snr_max``: the strongest SNR bin of :data:`SNR_MIX` an episode has (0 low, 1 medium, 2 high, the
    default: every bin up to it in equal shares, so 0 trains on the weakest signals only);
    ``grid``: 20 or 30 (the benchmark's areas); ``max_steps``: the benchmark's 120 by default;
    ``sensing``: the team's model (``"realistic"`` or None: :data:`TEAM_SENSING`; it must have the
    world's cell size, the exact line of sight and obstructions that block it); ``pool``: episodes
    drawn at a time (each is played once, then a fresh pool is drawn); the rest: the domain
    randomisation of the module docstring (defaults: none); ``prior_background_low``,
    ``prior_background_high``, ``prior_background_levels`` (all or none): the team estimator's
    background prior, uniform over that range at that many levels instead of the model's 10-50 counts/s
    at 8 (:func:`~medc_training.radbench.physics.team_sensing`), recorded in :attr:`attributes`.
    """

    def __init__(self, num_envs: int = 1, device: str | torch.device = "cpu", seed: int | None = None,
                 agents: int = 3, walls: int = 7, grid: int = 20, max_steps: int = MAX_STEPS,
                 reward_shaping: bool = False, copy_obs: bool = True, observation: str = DEFAULT_OBSERVATION,
                 sensing: SensingModel | str | dict | None = None, pool: int = 2048,
                 transmission_max: float = 0.0, efficiency_spread: float = 0.0, strength_spread: float = 1.0,
                 background_low: float | None = None, background_high: float | None = None,
                 position_noise_max: float = 0.0, walls_min: int = 0,
                 snr_max: int = len(SNR_MIX) - 1, prior_background_low: float | None = None,
                 prior_background_high: float | None = None,
                 prior_background_levels: int | None = None) -> None:
        if grid not in GRIDS:
            raise ValueError(f"the benchmark's world has grids of {sorted(GRIDS)} cells, got {grid!r}")
        if isinstance(walls, bool) or not isinstance(walls, int) or walls not in OBSTRUCTION_COUNTS:
            raise ValueError("walls (the most obstructions of an episode) must be "
                             f"0..{max(OBSTRUCTION_COUNTS)}, got {walls!r}")
        if isinstance(walls_min, bool) or not isinstance(walls_min, int) or not 0 <= walls_min <= walls:
            raise ValueError(f"walls_min (the fewest obstructions of an episode) must be 0..walls ({walls}), "
                             f"got {walls_min!r}")
        if isinstance(snr_max, bool) or not isinstance(snr_max, int) or not 0 <= snr_max < len(SNR_MIX):
            raise ValueError("snr_max (the strongest SNR bin of an episode: 0 low, 1 medium, 2 high) "
                             f"must be 0..{len(SNR_MIX) - 1}, got {snr_max!r}")
        if isinstance(pool, bool) or not isinstance(pool, int) or not 1 <= pool <= 100_000:
            raise ValueError(f"pool must be an integer in 1..100000, got {pool!r}")
        self.randomisation = _randomisation(dict(
            transmission_max=transmission_max, efficiency_spread=efficiency_spread,
            strength_spread=strength_spread, position_noise_max=position_noise_max,
            background_low=background_low, background_high=background_high))
        self.prior = background_prior(dict(zip(PRIOR_OPTIONS, (
            prior_background_low, prior_background_high, prior_background_levels), strict=True)))
        if sensing is None or sensing == TEAM_SENSING.name:
            sensing = team_sensing(self.prior)
        elif self.prior is not None:
            raise ValueError("the background prior options widen the team's own model; give them "
                             f"without sensing (got sensing {str(sensing)[:40]!r})")
        sensing = parse_sensing(sensing)
        spec = GRIDS[grid]
        if sensing.cell_size_m != spec.cell_m or sensing.line != "exact" or sensing.attenuation != 0.0:
            raise ValueError("the team's sensing model must have the world's cell size, the exact line of "
                             "sight and obstructions that block it (attenuation 0), e.g. 'realistic'")
        super().__init__(num_envs=num_envs, device=device, seed=seed, agents=agents, walls=0, grid=grid,
                         max_steps=max_steps, reward_shaping=reward_shaping, copy_obs=copy_obs,
                         observation=observation, sensing=sensing, posterior=True, end_on_find=True)
        self.num_walls = walls
        self.walls_min = walls_min
        self.snr_max = snr_max
        self.cell_m = spec.cell_m
        self.pool_size = pool
        self._slots = max(1, max(OBSTRUCTION_COUNTS))
        self.memory = TeamMemory(self.observation, self.num_envs, self.grid, self.device, self.sensing,
                                 posterior=True, max_walls=self._slots, rule_out=True)
        self._episodes: dict[str, torch.Tensor] | None = None
        self._next = 0
        b = self.num_envs
        #: Per environment: the current episode's departures from the team's model.
        self._departs = {"transmission": torch.zeros(b, device=self.device),
                         "efficiency": torch.ones(b, device=self.device),
                         "position_noise": torch.zeros(b, device=self.device)}

    @property
    def attributes(self) -> dict[str, Any]:
        return {"agents": self.num_agents, "walls": self.num_walls, "grid": self.grid,
                "max_steps": self.max_steps, "sensing": self.sensing.name, "world": WORLD,
                **({"walls_min": self.walls_min} if self.walls_min else {}),
                **({"snr_max": self.snr_max} if self.snr_max < len(SNR_MIX) - 1 else {}),
                **({} if self.prior is None else dict(zip(PRIOR_OPTIONS, self.prior, strict=True))),
                **self.randomisation}

    def _draw_pool(self) -> None:
        seed = TRAIN_SEED_BASE + int(torch.randint(0, 2**31 - 1, (1,), generator=self.generator,
                                                   device=self.device))
        episodes = draw_episodes(self.grid, self.num_agents, self.num_walls, self.pool_size, seed,
                                 self.walls_min, self.snr_max)
        tensors = episode_tensors(episodes, self.grid, self._slots, self.device)
        tensors.update(_draw_departures(self.randomisation, tensors, seed, self.device))
        self._episodes, self._next = tensors, 0

    def _take_layouts(self, k: int) -> dict[str, torch.Tensor]:
        parts: list[dict[str, torch.Tensor]] = []
        while k > 0:
            if self._episodes is None or self._next >= len(self._episodes["target"]):
                self._draw_pool()
            take = min(k, len(self._episodes["target"]) - self._next)
            parts.append({key: v[self._next:self._next + take] for key, v in self._episodes.items()})
            self._next += take
            k -= take
        lay = parts[0] if len(parts) == 1 else {key: torch.cat([p[key] for p in parts]) for key in parts[0]}
        self._fresh = {key: lay[key] for key in self._departs}
        return lay

    def _reseeded(self) -> None:
        self._episodes, self._next = None, 0

    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        super()._start_episodes(rows)
        for key, value in self._fresh.items():  # the new episodes' departures, from their layouts
            if rows is None:
                self._departs[key] = value.clone()
            else:
                self._departs[key][rows] = value

    def _read(self, lay: dict[str, torch.Tensor]) -> torch.Tensor:
        noise = lay["position_noise"]
        if bool((noise > 0).any()):
            k, n = lay["positions"].shape[:2]
            off = torch.rand((k, n), generator=self.generator, device=self.device) < noise.unsqueeze(1)
            way = torch.randint(1, 9, (k, n), generator=self.generator, device=self.device)
            lay = {**lay, "positions": jittered_positions(lay["positions"], torch.where(off, way, 0),
                                                          lay["walls"])}
        return torch.poisson(world_rates(self.sensing, self.cell_m, lay), generator=self.generator)

    def _episode_state(self) -> dict[str, torch.Tensor]:
        return {**super()._episode_state(), **self._departs}


def _randomisation(given: dict[str, Any]) -> dict[str, float]:
    """The checked randomisation options of ``given`` (each of :data:`RANDOMISATION_OPTIONS`) that
    differ from none (the attributes' form)."""
    out: dict[str, float] = {}
    for name, (default, lo, hi) in _SPREADS.items():
        value = given[name]
        if isinstance(value, bool) or not isinstance(value, int | float) or not lo <= value <= hi:
            raise ValueError(f"{name} must be a number in [{lo}, {hi}], got {value!r}")
        if value != default:
            out[name] = float(value)
    low, high = (given[name] for name in _BACKGROUND)
    if (low is None) != (high is None):
        raise ValueError("give background_low and background_high together (a background range in counts/s)")
    if low is not None:
        for name in _BACKGROUND:
            value = given[name]
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 10_000.0:
                raise ValueError(f"{name} must be counts/s in [0, 10000], got {value!r}")
        if low > high:
            raise ValueError(f"background_low {low} is above background_high {high}")
        out.update(background_low=float(low), background_high=float(high))
    return out


def _draw_departures(options: dict[str, float], tensors: dict[str, torch.Tensor], seed: int,
                     device: torch.device) -> dict[str, torch.Tensor]:
    """Per episode of a pool: its departures from the team's model under ``options`` (the strength
    and background replaced where they are randomised), from a stream of the pool's seed."""
    k = len(tensors["target"])
    rng = np.random.default_rng([seed, 2])
    u = torch.from_numpy(rng.random((5, k))).to(device=device, dtype=torch.float32)
    out = {"transmission": options.get("transmission_max", 0.0) * u[0],
           "efficiency": 1.0 + options.get("efficiency_spread", 0.0) * (2.0 * u[1] - 1.0),
           "position_noise": options.get("position_noise_max", 0.0) * u[2]}
    spread = options.get("strength_spread", 1.0)
    if spread != 1.0:
        out["strength"] = tensors["strength"] * spread ** (2.0 * u[3] - 1.0)
    if "background_low" in options:
        lo, hi = options["background_low"], options["background_high"]
        out["background"] = lo + (hi - lo) * u[4]
    return out

