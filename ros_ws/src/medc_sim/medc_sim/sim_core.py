"""The simulator's world: one target-localization environment, stepped by the team's moves.

No ROS in here: :class:`SimCore` is the training environment's batched core with B=1 (built
with the same ``make_batched`` call and seed as training, so it produces the same episodes),
plus what a real UAV would publish that the core keeps internal (positions, raw readings,
walls), read through the core's read-only state view (``env.state(0)``). The simulator node
only converts this to and from messages.

Two worlds (``SimConfig.world``): ``grid``, the grid world of the sensing presets, and
``radbench``, the field benchmark's (``make_batched(..., world="radbench")``:
``medc_training.radbench.world.BenchWorld``: solid obstructions, ``S / d² + B`` counts, fresh
benchmark episodes drawn :data:`RADBENCH_POOL` at a time).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

#: The worlds the simulator runs: the grid world and the field benchmark's.
WORLDS: tuple[str, ...] = ("grid", "radbench")
#: Benchmark episodes the radbench world draws at a time (each played once, then a fresh pool):
#: a training world draws 2048, which takes the simulator seconds to start.
RADBENCH_POOL = 64


def check_world_options(config: SimConfig) -> None:
    """Refuse a ``config`` whose options do not apply to its world: an unknown world, and in the
    benchmark's world an end rule other than ``source`` (its core ends an episode when a UAV comes
    within the success radius), a grid other than its areas, more obstructions than it draws or a
    sensing preset other than ``realistic`` (its team model's). Raises ValueError saying what to set."""
    if config.world not in WORLDS:
        raise ValueError(f"world must be one of {', '.join(WORLDS)}, got {str(config.world)[:40]!r}")
    if config.world != "radbench":
        return
    from medc_training.radbench.scenario import GRIDS, OBSTRUCTION_COUNTS

    if config.end_on != "source":
        raise ValueError(f"end_on {config.end_on!r} does not apply to the radbench world: its episodes end "
                         "when a UAV comes within 1.1 cells of the source (or at max_steps): set end_on "
                         "source")
    if config.grid not in GRIDS:
        raise ValueError(f"the radbench world has grids of {' or '.join(map(str, sorted(GRIDS)))} cells, got "
                         f"grid {config.grid}; set grid to one of them")
    if isinstance(config.walls, bool) or config.walls not in OBSTRUCTION_COUNTS:
        raise ValueError("walls (the most obstructions of a radbench episode) must be "
                         f"0..{max(OBSTRUCTION_COUNTS)}, got {config.walls!r}")
    if config.sensing != "realistic":
        raise ValueError(f"the radbench world senses with the realistic preset's team model, got sensing "
                         f"{str(config.sensing)[:40]!r}; set sensing realistic")


@dataclass(frozen=True)
class SimConfig:
    """The scenario the simulator runs (the same options as ``make_batched``)."""

    agents: int = 3
    walls: int = 2
    grid: int = 30
    max_steps: int = 100
    seed: int = 0
    #: Poisson counts on the paper-simple preset's readings; a preset that always counts them
    #: (realistic) does so whatever this says.
    noise: bool = False
    #: The sensing preset (``medc_training.envs.tl_sensing.SENSING_PRESETS``): how readings are made
    #: and when an agent has found the source (docs/ros-reference.md, "Sensor model").
    sensing: str = "paper-simple"
    #: What ends an episode besides max_steps (medc_sim.episode_end): ``source``, ``declaration`` or
    #: ``either``.
    end_on: str = "source"
    #: The world simulated (:data:`WORLDS`): ``grid`` or ``radbench``, the field benchmark's.
    world: str = "grid"


@dataclass
class EpisodeResult:
    """How one episode ended."""

    episode: int
    length: int
    success: bool
    truncated: bool
    reward: float
    #: ``source`` (a UAV found it), ``declaration`` (the team declared it), ``max_steps``.
    ended_by: str = ""
    #: For a declaration: cells from the declared cell to the source.
    error: float | None = None


@dataclass
class StepResult:
    """What one team step did; ``finished`` is set when it ended the episode."""

    reward: float
    finished: EpisodeResult | None = None


@dataclass
class SimCore:
    """One environment (B=1) and the episode counter."""

    config: SimConfig
    env: object = field(init=False)
    episode: int = field(init=False, default=0)
    results: list[EpisodeResult] = field(init=False, default_factory=list)
    #: Every applied step as (episode, step, actions), when ``record`` is set (tests, debugging).
    record: bool = False
    trace: list[tuple[int, int, list[int | None]]] = field(init=False, default_factory=list)

    def __post_init__(self) -> None:
        from medc_training.envs import make_batched
        from medc_training.envs.names import TARGET_LOCALIZATION
        from medc_training.envs.tl_sensing import parse_sensing

        from medc_sim.episode_end import check_end_rule

        c = self.config
        check_end_rule(c.end_on)
        check_world_options(c)
        if c.world == "radbench":
            # Readings are always Poisson counts there, and a UAV within the success radius ends the
            # episode: the grid world's noise and end_on_find do not apply.
            self.env = make_batched(TARGET_LOCALIZATION, num_envs=1, device="cpu", seed=c.seed,
                                    world="radbench", agents=c.agents, walls=c.walls, grid=c.grid,
                                    max_steps=c.max_steps,
                                    reward_shaping=False, sensing=c.sensing, observation="maps",
                                    pool=RADBENCH_POOL)
            self.env.reset()
            return
        model = parse_sensing(c.sensing)
        self.env = make_batched(
            TARGET_LOCALIZATION,
            num_envs=1,
            device="cpu",
            seed=c.seed,
            agents=c.agents,
            walls=c.walls,
            grid=c.grid,
            max_steps=c.max_steps,
            reward_shaping=False,
            # None: the preset's (realistic always counts Poisson noise and refuses False).
            noise=None if model.noise else c.noise,
            sensing=model.name,
            # The agents build their own observations from the messages; the simulator needs none,
            # and the paper's maps are the cheapest to keep.
            observation="maps",
            # Under 'declaration' finding the source does not end the episode: the team must say it.
            end_on_find=c.end_on != "declaration",
        )
        self.env.reset()

    @property
    def num_agents(self) -> int:
        return self.env.num_agents

    @property
    def num_actions(self) -> int:
        return self.env.num_actions

    @property
    def noise(self) -> bool:
        """Whether readings are Poisson counts (the ``noise`` option, or the preset's)."""
        return bool(self.env.noise)

    @property
    def sensing(self):
        """The sensing model (``medc_training.envs.tl_sensing.SensingModel``) the readings follow."""
        return self.env.sensing

    @property
    def step(self) -> int:
        """Steps taken in the current episode (0 right after reset)."""
        return self.env.state(0).step

    def positions(self) -> list[tuple[int, int]]:
        """Each agent's cell (row, col), in agent order."""
        return list(self.env.state(0).positions)

    def readings(self) -> list[float]:
        """Each agent's raw reading (counts/s) at its current cell, noise included (under the
        realistic preset: Poisson counts of the episode's unknown strength and background): exactly
        what the core recorded in its memory, so the agents rebuild the core's observation."""
        return list(self.env.state(0).readings)

    def walls(self) -> torch.Tensor:
        """bool [H,W] wall cells of the current episode (a copy)."""
        return self.env.state(0).walls

    def target(self) -> tuple[int, int]:
        return self.env.state(0).target

    def advance(self, actions: list[int | None]) -> StepResult:
        """Apply one move per agent; ``None`` = the agent stays where it is.

        Raises:
            ValueError: wrong number of actions or an action outside 0..num_actions-1.
        """
        if len(actions) != self.num_agents:
            raise ValueError(f"need {self.num_agents} actions, got {len(actions)}")
        if self.record:
            self.trace.append((self.episode, self.step, list(actions)))
        stay = [i for i, a in enumerate(actions) if a is None]
        acts = torch.tensor([[0 if a is None else int(a) for a in actions]], dtype=torch.long)
        # The core keeps a held agent in place for this step only.
        self.env.hold(0, stay)
        out = self.env.step(acts)
        result = StepResult(reward=float(out.reward[0]))
        if bool(out.terminated[0] | out.truncated[0]):
            result.finished = EpisodeResult(
                episode=self.episode,
                length=int(out.episode_length[0]),
                success=bool(out.success[0]),
                truncated=bool(out.truncated[0]),
                reward=result.reward,
                ended_by="source" if bool(out.success[0]) else "max_steps",
            )
            self.results.append(result.finished)
            self.episode += 1
        return result

    def end_by_declaration(self, cell: tuple[int, int]) -> EpisodeResult:
        """End the current episode now on the team's declaration that the source is at ``cell``
        (row, col): a success when a UAV on that cell would find it (the preset's success radius).
        The next episode starts (the one the core's own rules would have started)."""
        from medc_sim.episode_end import judge

        error, correct = judge(cell, self.target(), self.sensing.success_radius)
        finished = EpisodeResult(episode=self.episode, length=self.step, success=correct, truncated=False,
                                 reward=0.0, ended_by="declaration", error=error)
        self.env.end_episode(0)
        self.results.append(finished)
        self.episode += 1
        return finished
