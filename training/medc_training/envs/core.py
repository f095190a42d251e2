"""What every batched environment core shares: the step result, seeding, option checks, the
read-only state view.

A batched core steps ``num_envs`` independent copies of one application at once, with
torch tensor operations only (no numpy and no Python loop over the batch in ``step``), so
the same code runs on a CUDA device. Finished environments reset automatically; the last
observation of the finished episode is returned in :attr:`StepOutput.final_obs` so that
PPO can bootstrap truncated episodes.

Code outside a core reads its state through :meth:`BatchedEnv.state` (a snapshot of copies)
and changes it only through its methods (``reset``, ``step``, :meth:`BatchedEnv.hold`,
:meth:`BatchedEnv.end_episode`,
:meth:`BatchedEnv.keep_pictures`), never by writing its tensors.
"""

from __future__ import annotations

import secrets
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch


@dataclass
class StepOutput:
    """Result of :meth:`BatchedEnv.step` for ``B`` environments of ``N`` agents.

    obs:            float32 [B,N,C,H,W] next observation; already the new episode's first
                    observation where the environment finished (auto-reset).
    mask:           bool [B,N,A] allowed actions for ``obs`` (True = allowed).
    reward:         float32 [B] team reward, shared by the team's agents.
    terminated:     bool [B] the task was completed (success).
    truncated:      bool [B] max_steps reached without success (PPO bootstraps these).
    final_obs:      float32 [B,N,C,H,W] last observation of the finished episode, valid only
                    where ``terminated | truncated`` (it may be the same tensor as ``obs``
                    when no environment finished).

    With ``copy_obs=False`` (an option of the cores) ``obs`` and ``final_obs`` are buffers
    the env reuses: the next ``step``/``reset`` overwrites them, so copy what you keep.
    episode_length: int64 [B] steps taken in the finished episode (valid where done).
    success:        bool [B] the finished episode succeeded (valid where done).
    """

    obs: torch.Tensor
    mask: torch.Tensor
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    final_obs: torch.Tensor
    episode_length: torch.Tensor
    success: torch.Tensor

    @property
    def done(self) -> torch.Tensor:
        """bool [B]: the episode ended this step (terminated or truncated)."""
        return self.terminated | self.truncated


@dataclass(frozen=True)
class EnvState:
    """A read-only snapshot of one environment of a batched core (:meth:`BatchedEnv.state`).

    Its fields are copies: the core moving on does not change them, and changing them does not
    change the core.

    step:      steps taken in the current episode (0 right after a reset).
    positions: each agent's cell (row, col), in agent order.
    mask:      bool [N,A] the moves allowed now (True = allowed).
    """

    step: int
    positions: tuple[tuple[int, int], ...]
    mask: torch.Tensor


class BatchedEnv(ABC):
    """Interface shared by the three batched cores (see the concrete classes).

    Attributes: ``num_envs``, ``num_agents``, ``num_actions``, ``obs_shape`` (C, H, W),
    ``observation`` (the :class:`~medc_training.envs.observation.ObservationSpec` it produces),
    ``device``, ``name``, ``attributes`` (dict of the environment's descriptive features).

    The episode is this class's: :meth:`reset` and :meth:`step` own the moves, the step clock
    ``t``, truncation at ``max_steps``, the final observation and auto-reset. An application
    implements :meth:`_start_episodes`, :meth:`_transition` and :meth:`_observe` (plus its oracle)
    and keeps ``positions`` int64 [B,N,2], ``blocked_pad`` (:func:`~medc_training.envs.grid.pad_blocked`),
    ``_deltas`` (:func:`~medc_training.envs.grid.action_deltas`), ``max_steps`` and ``copy_obs``.
    """

    name: str = ""
    num_envs: int
    num_agents: int
    num_actions: int
    obs_shape: tuple[int, int, int]
    device: torch.device
    max_steps: int

    def __init__(self, num_envs: int, device: str | torch.device, seed: int | None) -> None:
        self.num_envs = check_int("num_envs", num_envs, 1, 1_000_000)
        try:
            self.device = torch.device(device)
        except (RuntimeError, TypeError) as exc:
            raise ValueError(
                f"device must be a torch device such as 'cpu' or 'cuda', got {device!r}"
            ) from exc
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(f"device {device!r} requested but CUDA is not available here; use 'cpu'")
        self.generator = torch.Generator(device=self.device)
        self._seed(seed)

    def _seed(self, seed: int | None) -> None:
        if seed is None:
            seed = secrets.randbits(63)
        self.generator.manual_seed(check_int("seed", seed, 0, 2**63 - 1))

    @property
    @abstractmethod
    def attributes(self) -> dict[str, Any]:
        """The environment's descriptive features (what a model registry compares)."""

    # -- the episode: one place for reset, moves, the clock, truncation and auto-reset ---------
    def reset(self, seed: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Start a new episode in every environment; returns (obs [B,N,C,H,W], mask [B,N,A]).

        With ``seed`` the core's generator restarts from it (and :meth:`_reseeded` forgets
        anything drawn ahead, such as a pool of layouts)."""
        from medc_training.envs.grid import move_mask

        if seed is not None:
            self._seed(seed)
            self._reseeded()
        self._start_episodes(None)
        self._started = True
        self._obs = self._observe()
        self._final_obs = None if self.copy_obs else torch.zeros_like(self._obs)
        self.mask = move_mask(self.positions, self.blocked_pad, self._deltas)
        return (self._obs.clone() if self.copy_obs else self._obs), self.mask

    def step(self, actions: torch.Tensor) -> StepOutput:
        """Apply one action per agent (int64 [B,N]); finished environments auto-reset.

        The one episode loop of every core: moves (a disallowed move leaves the agent in place),
        the application's :meth:`_transition`, the observation, the step clock, truncation at
        ``max_steps``, the final observation of finished episodes and their restart."""
        from medc_training.envs.grid import move_mask

        if not self._started:
            raise RuntimeError("call reset() before step()")
        actions = self._check_actions(actions)
        allowed = self.mask.gather(2, actions.unsqueeze(2))  # [B,N,1]
        previous = self.positions
        self.positions = self.positions + self._deltas[actions] * allowed
        reward, success = self._transition(actions)
        self._observe_step(previous)
        self.t += 1
        episode_length = self.t.clone()
        truncated = (self.t >= self.max_steps) & ~success
        done = success | truncated
        if bool(done.any()):
            rows = done.nonzero().squeeze(1)
            if self.copy_obs:
                final_obs = self._obs.clone()
            else:
                final_obs = self._final_obs
                final_obs[rows] = self._obs[rows]
            if self._keep_final_pictures and not self.observes_pictures:
                self._final_pictures = {int(r): self.picture_maps(int(r)) for r in rows}
            self._start_episodes(rows)
            self._obs[rows] = self._observe(rows)
            obs = self._obs.clone() if self.copy_obs else self._obs
        else:
            obs = self._obs.clone() if self.copy_obs else self._obs
            final_obs = obs if self.copy_obs else self._final_obs
        self.mask = move_mask(self.positions, self.blocked_pad, self._deltas)
        return StepOutput(obs, self.mask, reward, success, truncated, final_obs, episode_length,
                          success.clone())

    # -- what an application implements ----------------------------------------------------
    @abstractmethod
    def _start_episodes(self, rows: torch.Tensor | None) -> None:
        """Draw new episodes in ``rows`` (all environments when None): ``positions``,
        ``blocked_pad``, the step clock ``t`` (0) and the application's own state."""

    @abstractmethod
    def _transition(self, actions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The application's rules after the moves (``positions`` already moved): update its
        state and return (team reward float32 [B], success bool [B])."""

    @abstractmethod
    def _observe(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        """float32 [B,N,C,H,W]: every agent's observation of the current state ([R,N,C,H,W] of
        ``rows`` only, when given)."""

    def _observe_step(self, previous: torch.Tensor) -> None:
        """Bring ``_obs`` up to date after a step (``previous`` = positions before the moves).
        A core whose observation changes in a few cells per step overrides this to update in
        place; the default rebuilds it."""
        self._obs = self._observe()

    def _reseeded(self) -> None:  # noqa: B027 (a hook: most cores draw nothing ahead)
        """Forget whatever was drawn ahead from the old generator state (nothing by default)."""

    @property
    def observes_pictures(self) -> bool:
        """Whether the observations are the absolute maps a picture is drawn from (then a
        finished episode's picture is its final observation)."""
        spec = self.observation
        return spec.view == "maps" and not spec.source_views

    @abstractmethod
    def oracle_action_scores(self) -> torch.Tensor:
        """float32 [B,N,A] scripted expert's scores for the current state (-inf = invalid)."""

    @property
    def observation_name(self) -> str:
        """The observation's name ('maps', 'ego9', 'ego6+estimate', ...), as manifests record it."""
        return self.observation.name

    @property
    def observation_channels(self) -> tuple[str, ...]:
        """The name of each observation channel, in order (its application's names for the view)."""
        from medc_training.envs.descriptor import application

        return application(self.name).channels(self.observation)

    def current_obs(self, index: int) -> torch.Tensor:
        """float32 [N,C,H,W]: the current observations of environment ``index`` (a copy)."""
        return self._obs[index].clone()

    _started = False
    _keep_final_pictures = False

    @property
    def keep_final_pictures(self) -> bool:
        """Whether the picture maps of episodes are kept as they finish, for
        :meth:`final_picture_maps` (off unless a renderer asked, with :meth:`keep_pictures`)."""
        return self._keep_final_pictures

    def keep_pictures(self, keep: bool = True) -> None:
        """Keep (or stop keeping) the picture maps of episodes as they finish, for a renderer that
        draws :meth:`final_picture_maps` after the core has reset."""
        self._keep_final_pictures = check_bool("keep", keep)

    def _check_index(self, index: int) -> int:
        if not self._started:
            raise RuntimeError("call reset() before reading or changing the environment's state")
        return check_int("index", index, 0, self.num_envs - 1)

    def state(self, index: int) -> EnvState:
        """A read-only snapshot of environment ``index`` (see :class:`EnvState`; a core may return
        a subclass with more of its state)."""
        index = self._check_index(index)
        return EnvState(
            step=int(self.t[index]),
            positions=tuple((int(r), int(c)) for r, c in self.positions[index].tolist()),
            mask=self.mask[index].clone(),
        )

    def hold(self, index: int, agents: Sequence[int]) -> None:
        """Keep ``agents`` of environment ``index`` where they are on the next :meth:`step`.

        Their moves in that step are disallowed, which leaves an agent in place whatever action it
        is given; the mask is recomputed after every step, so the hold lasts one step. Masks that
        ``reset``/``step`` returned before are not changed.
        """
        index = self._check_index(index)
        rows = [check_int("agent", a, 0, self.num_agents - 1) for a in agents]
        if rows:
            self.mask = self.mask.clone()
            self.mask[index, rows] = False

    def end_episode(self, index: int) -> None:
        """End environment ``index``'s episode now and start its next one, by a caller's own rule
        (e.g. a simulator that ends episodes on the team's declaration that it has localised the
        source). The next episode is the one the core's own rules would have started; the step
        clock restarts at 0 and the move mask of the row is recomputed (a :meth:`hold` on it lapses).
        """
        from medc_training.envs.grid import move_mask

        index = self._check_index(index)
        rows = torch.tensor([index], device=self.device)
        self._start_episodes(rows)
        self._obs[rows] = self._observe(rows)
        self.mask = self.mask.clone()
        self.mask[rows] = move_mask(self.positions[rows], self.blocked_pad[rows], self._deltas)

    def picture_maps(self, index: int) -> torch.Tensor:
        """float32 [N,C,G,G]: the absolute maps a picture of environment ``index`` is drawn from
        (the observations, unless a core's observations are not absolute maps)."""
        return self.current_obs(index)

    def final_picture_maps(self, index: int, final_obs: torch.Tensor) -> torch.Tensor:
        """:meth:`picture_maps` of the episode that just ended in environment ``index``."""
        return final_obs[index] if self.observes_pictures else self._final_pictures[index]

    def render_extras(self, index: int) -> dict[str, Any]:
        """What a picture of environment ``index`` needs beyond the observation maps."""
        return {}

    def _check_actions(self, actions: torch.Tensor) -> torch.Tensor:
        actions = torch.as_tensor(actions, device=self.device)
        if actions.shape != (self.num_envs, self.num_agents):
            raise ValueError(
                f"actions must have shape (num_envs, num_agents) = {(self.num_envs, self.num_agents)}, "
                f"got {tuple(actions.shape)}"
            )
        if actions.dtype.is_floating_point or actions.dtype == torch.bool:
            raise ValueError(f"actions must be an integer tensor, got {actions.dtype}")
        lo, hi = torch.aminmax(actions)
        if int(lo) < 0 or int(hi) >= self.num_actions:
            raise ValueError(
                f"actions must be in 0..{self.num_actions - 1}, got values in {int(lo)}..{int(hi)}"
            )
        return actions.long()


def check_int(name: str, value: Any, lo: int, hi: int) -> int:
    """Return ``value`` as an int if ``lo <= value <= hi``; otherwise raise ValueError saying so."""
    if isinstance(value, bool) or not hasattr(value, "__index__"):
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {value!r}")
    value = int(value.__index__())
    if not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer in {lo}..{hi}, got {value}")
    return value


#: The longest episode (``max_steps``) any core accepts.
MAX_EPISODE_STEPS = 1_000_000


def check_core_options(grid: Any, agents: Any, max_steps: Any, *, grid_range: tuple[int, int],
                       max_agents: Callable[[int], int]) -> tuple[int, int, int]:
    """The options every core takes, checked the same way; returns (grid, agents, max_steps).

    ``grid`` (side of the square area) must be in ``grid_range``, ``agents`` in
    1..``max_agents(grid)`` and ``max_steps`` in 1..:data:`MAX_EPISODE_STEPS`; otherwise
    ValueError names the option and what is allowed.
    """
    grid = check_int("grid", grid, *grid_range)
    agents = check_int("agents", agents, 1, max_agents(grid))
    max_steps = check_int("max_steps", max_steps, 1, MAX_EPISODE_STEPS)
    return grid, agents, max_steps


def check_bool(name: str, value: Any) -> bool:
    """Return ``value`` if it is a bool; otherwise raise ValueError."""
    if not isinstance(value, bool):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return value


def maps_channels(channels: tuple[str, ...]):
    """The channel names of a :class:`MapsObservationEnv` application with absolute maps
    ``channels`` (channel 0 = own location), per view: in a window channel 0 reads "off the grid"."""
    def names(spec) -> tuple[str, ...]:
        return channels if spec.view == "maps" else ("off_grid", *channels[1:])
    return names


class MapsObservationEnv(BatchedEnv):
    """Observation of the cores whose state is drawn as absolute maps (fleet coordination, maze
    cleaning): the maps themselves, or the agent-centred window of each (``observation`` option).

    A subclass provides ``_observe_maps()`` (float32 [B,N,C,G,G], its absolute maps, channel 0 =
    own location) and calls :meth:`_set_observation` in its constructor.

    ``maps`` is the paper's absolute maps; ``egoR`` shows each map in a (2R+1)×(2R+1) window
    centred on the agent, with channel 0 (own location, always the centre in such a window)
    replaced by "off the grid" (1 outside), and the channels named in ``WALL_CHANNELS`` reading 1
    off the grid. These applications have no source estimate: ``+estimate`` and ``+posterior`` are
    refused.
    """

    #: Channels that mean "cannot go there": off-grid cells read 1 in an ego window.
    WALL_CHANNELS: tuple[int, ...] = ()
    #: The names of the application's absolute maps (channel 0 = own location).
    CHANNELS: tuple[str, ...] = ()

    def _set_observation(self, observation: Any, channels: int) -> None:
        """Validate the ``observation`` option and set ``observation`` and ``obs_shape``."""
        from medc_training.envs.descriptor import application

        spec = application(self.name).view(observation)
        self.observation = spec
        self.obs_shape = spec.shape(self.grid, channels)
        self._outside = torch.zeros(channels)
        self._outside[[0, *self.WALL_CHANNELS]] = 1.0

    def _observe(self, rows: torch.Tensor | None = None) -> torch.Tensor:
        maps = self._observe_maps()
        if self.observation.view == "ego":
            from medc_training.envs.grid import agent_windows

            maps[:, :, 0] = 0.0
            maps = agent_windows(maps, self.positions, self.observation.radius,
                                 self._outside.to(maps.device))
        return maps if rows is None else maps[rows]

    def picture_maps(self, index: int) -> torch.Tensor:
        return self._observe_maps()[index]

    @abstractmethod
    def _observe_maps(self) -> torch.Tensor:
        """float32 [B,N,C,G,G]: every agent's absolute maps of the current state."""
