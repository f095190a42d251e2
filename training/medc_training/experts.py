"""Experts for MEDC and IL-assisted RL: anything that maps observations to action scores.

An expert answers ``scores(obs [M,C,H,W], mask [M,A]) -> float32 [M,A]``: higher is better,
``-inf`` means "not suggested" (an expert with no opinion about an action, or an invalid
move). MEDC lets the agent take the best-ranked *suggested* action that its own policy
finds probable enough (see :mod:`medc_training.medc`).

Kinds:
- :class:`BundleExpert` — a trained policy bundle of any architecture (scores = log-probs).
- :class:`OracleExpert` — scripted, from the environment's BFS oracle (needs the env).
- :class:`ControllerExpert` — a classical search controller of :mod:`medc_training.controllers`
  (``infotaxis``, ``space-aware``, ...): it reads the team's memory in the environment, as a searcher
  in the field would, and is asked only for the rows of guided episodes.
- :class:`RandomExpert` — a random ranking of the valid moves every call.
- :class:`BiasedExpert` — always suggests the same action, whatever it sees.
- :class:`MaliciousExpert` — knows the right action (from an inner expert) and suggests
  the opposite direction: its score for ``a`` is the inner score for ``OPPOSITE[a]``.

Each expert carries ``attributes`` (the environment it was trained for, if known), from which
the trainer computes R_S by the contract's QoS rule (:mod:`medc_training.qos`).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from pathlib import Path

import torch

NEG_INF = float("-inf")


class ExpertError(ValueError):
    """An expert cannot be used with this environment (shape, actions, unknown spec)."""


class Expert(ABC):
    """Base class: subclasses implement :meth:`scores`."""

    name: str = "expert"
    attributes: dict | None = None

    @abstractmethod
    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """Action scores [M, A] for observations [M, C, H, W] (higher = better)."""

    def scores_rows(self, obs: torch.Tensor, mask: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        """Scores for the flattened rows ``rows`` of a full [B*N] batch.

        Observation-driven experts only look at those rows; the oracle needs the row index
        to find the agent in the environment.
        """
        return self.scores(obs[rows], mask[rows])

    def bind(self, env) -> Expert:
        """Attach the batched environment whose agents this expert advises; returns self.

        The learner calls it for every expert. An expert that advises from the observations alone
        (the default) ignores the environment; the oracle reads its state.
        """
        return self

    def check_compatible(self, obs_shape: Sequence[int], num_actions: int,
                         observation: str | None = None) -> None:
        """Raise ExpertError if this expert cannot advise on that observation/action space.

        ``observation`` names the environment's observation variant (target localization).
        The default accepts any space: random advice fits every environment.
        """
        return None


class BundleExpert(Expert):
    """A trained policy bundle (any architecture) used as an expert."""

    def __init__(self, bundle, name: str | None = None) -> None:
        self.bundle = bundle
        manifest = bundle.manifest
        env = manifest.get("environment", {}) or {}
        self.attributes = {k: v for k, v in env.items()
                           if isinstance(v, int | float) and not isinstance(v, bool)}
        self.application = manifest.get("application")
        from .nets import safe_repr  # the name comes from a file: shown sanitised in messages

        self.name = name or f"bundle:{safe_repr(manifest.get('architecture', {}).get('name', 'net'))[1:-1]}"

    @property
    def obs_shape(self) -> tuple:
        return tuple(self.bundle.obs_shape)

    @property
    def num_actions(self) -> int:
        return int(self.bundle.num_actions)

    def check_compatible(self, obs_shape: Sequence[int], num_actions: int,
                         observation: str | None = None, application: str | None = None) -> None:
        mine = self.bundle.observation
        if observation and mine and mine != observation:
            raise ExpertError(
                f"expert {self.name} takes the observation {mine!r}, but this environment produces "
                f"{observation!r}; use an expert trained on the same observation (or train with "
                f"--observation {mine})"
            )
        if self.obs_shape and tuple(self.obs_shape) != tuple(obs_shape):
            raise ExpertError(
                f"expert {self.name} was trained on observations of shape {self.obs_shape}, but this "
                f"environment produces {tuple(obs_shape)}; use an expert trained at the same grid size "
                "and observation channels"
            )
        if self.num_actions != num_actions:
            raise ExpertError(
                f"expert {self.name} has {self.num_actions} actions, this environment has {num_actions}"
            )
        if application and self.application and application != self.application:
            raise ExpertError(
                f"expert {self.name} was trained for {self.application!r}, not {application!r}"
            )

    @torch.no_grad()
    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        device = self.bundle.device
        probs = self.bundle.action_probs(obs.to(device), mask.to(device)).to(obs.device)
        scores = torch.log(probs.clamp_min(1e-12))
        return scores.masked_fill(~mask, NEG_INF)


class OracleExpert(Expert):
    """Scripted expert from the environment's oracle (BFS distance to the target)."""

    name = "oracle"

    def __init__(self, env=None) -> None:
        self.env = env

    def bind(self, env) -> OracleExpert:
        """Attach the batched environment whose agents this oracle advises; returns self."""
        self.env = env
        return self

    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        if self.env is None:
            raise ExpertError("OracleExpert needs the environment: call bind(env) first")
        full = self.env.oracle_action_scores().reshape(-1, mask.shape[-1]).to(obs.device)
        if full.shape[0] != obs.shape[0]:
            raise ExpertError(
                f"OracleExpert.scores needs the full batch of {full.shape[0]} agents, got {obs.shape[0]}; "
                "use scores_rows for a subset"
            )
        return full.masked_fill(~mask, NEG_INF)

    def scores_rows(self, obs: torch.Tensor, mask: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        if self.env is None:
            raise ExpertError("OracleExpert needs the environment: call bind(env) first")
        full = self.env.oracle_action_scores().reshape(-1, mask.shape[-1]).to(obs.device)
        return full[rows].masked_fill(~mask[rows], NEG_INF)


class ControllerExpert(Expert):
    """A classical search controller (:data:`medc_training.controllers.CONTROLLERS`) as an expert.

    Its scores are the controller's move scores for the bound target-localization core's current
    state (the team memory, not the observation: a searcher needs the posterior, which the agents'
    observations only summarise), computed only for the environments of the rows asked about. Its
    attributes are those of the environment it is bound to: a controller advises any environment
    its model covers, so the contract's QoS rule ranks it as an exact match.
    """

    def __init__(self, controller: str) -> None:
        from .controllers import CONTROLLERS

        if controller not in CONTROLLERS:
            raise ExpertError(f"unknown controller {str(controller)[:40]!r} for controller:NAME; "
                              f"choose one of {', '.join(CONTROLLERS)}")
        self.controller = controller
        self.name = f"controller:{controller}"
        self.env = None
        #: Environment rows (agents) this expert has scored: guided steps only.
        self.rows_scored = 0

    def bind(self, env) -> ControllerExpert:
        """Attach the target-localization core whose team this controller advises; returns self.
        Raises ExpertError when the controller cannot play that core (another application, or a
        posterior-reading controller on a core that keeps no posterior)."""
        from .controllers import _check

        try:
            _check(self.controller, env)
        except ValueError as exc:
            raise ExpertError(f"expert {self.name}: {exc}") from None
        self.env = env
        self.attributes = dict(getattr(env, "attributes", {}) or {})
        return self

    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        env = self._bound()
        rows = torch.arange(env.num_envs * env.num_agents, device=mask.device)
        if mask.shape[0] != rows.numel():
            raise ExpertError(f"{self.name}.scores needs the full batch of {rows.numel()} agents, got "
                              f"{mask.shape[0]}; use scores_rows for a subset")
        return self.scores_rows(obs, mask, rows)

    def scores_rows(self, obs: torch.Tensor, mask: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        from .controllers import controller_scores

        env = self._bound()
        n, a = env.num_agents, env.num_actions
        rows = rows.to(env.device)
        envs, slot = torch.unique(rows // n, return_inverse=True)
        team_mask = mask.to(env.device).view(env.num_envs, n, a)[envs]
        scores = controller_scores(self.controller, env, team_mask, envs=envs)  # [K,N,A]
        self.rows_scored += int(rows.numel())
        out = scores[slot, rows % n].to(obs.device)
        return out.masked_fill(~mask[rows.to(mask.device)], NEG_INF)

    def _bound(self):
        if self.env is None:
            raise ExpertError(f"{self.name} needs the environment: call bind(env) first")
        return self.env


class RandomExpert(Expert):
    """Suggests a uniformly random ranking of the valid moves (a useless expert)."""

    name = "random"

    def __init__(self, generator: torch.Generator | None = None) -> None:
        self.generator = generator

    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        noise = torch.rand(mask.shape, generator=self.generator, device="cpu").to(mask.device)
        return noise.masked_fill(~mask, NEG_INF)


class BiasedExpert(Expert):
    """Always suggests the same action, whatever it observes."""

    def __init__(self, action: int = 0) -> None:
        if action < 0:
            raise ExpertError(f"biased expert action must be >= 0, got {action}")
        self.action = int(action)
        self.name = f"biased:{action}"

    def check_compatible(self, obs_shape: Sequence[int], num_actions: int,
                         observation: str | None = None) -> None:
        if self.action >= num_actions:
            raise ExpertError(f"biased expert action {self.action} is not one of the {num_actions} actions")

    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        scores = torch.full(mask.shape, NEG_INF, device=mask.device)
        scores[:, self.action] = 0.0
        return scores.masked_fill(~mask, NEG_INF)


def default_opposite(num_actions: int) -> list[int]:
    """Opposite direction of each action for the 8-move compass (N, NE, ..., NW)."""
    if num_actions != 8:
        raise ExpertError(
            f"no default opposite-direction table for {num_actions} actions; pass opposite= explicitly"
        )
    return [(a + 4) % 8 for a in range(8)]


class MaliciousExpert(Expert):
    """Knows the right action (the inner expert's best) and suggests its opposite direction.

    ``opposite[a]`` is the action pointing the other way from ``a``; the malicious score of
    ``a`` is the inner expert's score of ``opposite[a]``, so its best-ranked action is the
    opposite of the inner expert's best and the whole ranking is mirrored.
    """

    def __init__(self, inner: Expert, opposite: Sequence[int] | None = None) -> None:
        self.inner = inner
        self.opposite = list(opposite) if opposite is not None else None
        self.attributes = inner.attributes
        self.name = f"malicious({inner.name})"

    def bind(self, env) -> MaliciousExpert:
        """Bind the inner expert (whose advice is mirrored) to ``env``; returns self."""
        self.inner.bind(env)
        return self

    def check_compatible(self, obs_shape: Sequence[int], num_actions: int,
                         observation: str | None = None) -> None:
        self.inner.check_compatible(obs_shape, num_actions, observation)
        if self.opposite is None:
            self.opposite = default_opposite(num_actions)
        if sorted(self.opposite) != list(range(num_actions)):
            raise ExpertError(f"opposite table {self.opposite} is not a permutation of {num_actions} actions")

    def _mirror(self, inner_scores: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        opposite = self.opposite or default_opposite(mask.shape[-1])
        index = torch.as_tensor(opposite, device=inner_scores.device)
        # Score the inner expert on every move (valid or not) so that an opposite which
        # is valid here keeps its rank even if the inner's best is blocked by a wall.
        return inner_scores[:, index].masked_fill(~mask, NEG_INF)

    def scores(self, obs: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        full = torch.ones_like(mask)
        return self._mirror(self.inner.scores(obs, full), mask)

    def scores_rows(self, obs: torch.Tensor, mask: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
        full = torch.ones_like(mask)
        return self._mirror(self.inner.scores_rows(obs, full, rows), mask[rows])


def parse_expert(spec: str, generator: torch.Generator | None = None, device: str = "cpu") -> Expert:
    """Build an expert from a CLI spec.

    ``PATH`` (a bundle file) | ``random`` | ``biased`` or ``biased:A`` | ``malicious:PATH`` |
    ``malicious:oracle`` | ``oracle`` | ``controller:NAME`` (a classical search controller, e.g.
    ``controller:space-aware``) | ``malicious:controller:NAME``.
    """
    if spec == "random":
        return RandomExpert(generator)
    if spec == "oracle":
        return OracleExpert()
    if spec.startswith("controller:"):
        return ControllerExpert(spec.split(":", 1)[1])
    if spec == "biased" or spec.startswith("biased:"):
        action = spec.split(":", 1)[1] if ":" in spec else "0"
        if not action.isdigit():
            raise ExpertError(f"biased expert needs an action index, e.g. biased:2, got {spec!r}")
        return BiasedExpert(int(action))
    if spec.startswith("malicious:"):
        inner = spec.split(":", 1)[1]
        if inner.startswith("malicious:"):
            raise ExpertError("malicious:malicious:... is not supported")
        return MaliciousExpert(parse_expert(inner, generator, device))
    path = Path(spec)
    if not path.is_file():
        raise ExpertError(
            f"expert {spec!r} is neither a bundle file nor one of: random, biased[:A], oracle, "
            "controller:NAME, malicious:PATH, malicious:oracle, malicious:controller:NAME"
        )
    from .bundle import load_bundle  # the bundle module is only needed for file experts

    return BundleExpert(load_bundle(path, device=device), name=path.stem)
