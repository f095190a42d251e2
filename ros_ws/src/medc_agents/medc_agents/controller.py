"""A classical controller as an agent's policy (no ROS here).

An agent node runs a controller of ``medc_training.controllers`` (``gradient``, ``greedy``,
``infotaxis`` and the information-driven searchers of ``medc_training.searchers``) by name
wherever it takes a policy bundle (the ``policy`` parameter, the policy topics). It decides its own
move with the controller's pure batched function, on the state its
:class:`~medc_agents.team_state.TeamObserver` keeps of the team (the team memory with its source
posterior, the walls, every agent's position and move mask of the step it observed): the team's
move scores [1,N,8] are those the batched core's ``controller_scores(name, env)`` gives for the
same state, and the agent takes the argmax of its own row, masked as a bundle's move is.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from medc_training.controllers import CONTROLLERS, COORDINATED, SEARCHERS, controller_scores
from medc_training.envs.names import TARGET_LOCALIZATION

#: The application every controller plays.
APPLICATION = TARGET_LOCALIZATION


def controller_name(source: object) -> str | None:
    """The controller ``source`` names (``greedy``, ``gradient``, ``infotaxis``; surrounding blanks
    ignored), or None when it names none (a bundle path, a content id). A name always means the
    controller: a bundle file so named in the working directory is given as ``./greedy``."""
    if not isinstance(source, str):
        return None
    name = source.strip()
    return name if name in CONTROLLERS else None


@dataclass
class ControllerPolicy:
    """A running controller, in the place of a :class:`~medc_agents.policy_slot.LoadedPolicy`."""

    controller: str
    #: Controllers have no network: nothing to batch across agents.
    bundle: None = None

    @property
    def source(self) -> str:
        return self.controller

    @property
    def description(self) -> str:
        return f"{self.controller} (classical controller)"


@dataclass
class TeamView:
    """The team's state as ``controller_scores`` reads a batched core (B = 1)."""

    memory: object
    positions: torch.Tensor  # int64 [1,N,2]
    walls: torch.Tensor  # bool [1,G,G]
    mask: torch.Tensor  # bool [1,N,8]
    noise: bool
    name: str = APPLICATION
    observation_name: str = "maps+estimate"


def team_view(observer, noise: bool = False, agents: slice | None = None) -> TeamView:
    """The :class:`TeamView` of ``observer``'s last observed step (after
    :meth:`~medc_agents.team_state.TeamObserver.observe`). ``noise``: the readings are Poisson counts
    (the simulator's ``noise``; always so under a sensing preset that counts them). ``agents``: only
    these agents' positions and masks (the team memory, which holds every agent's readings, stays
    whole).

    Raises:
        RuntimeError: the observer has observed no step yet.
    """
    if observer.positions is None:
        raise RuntimeError("no team step observed yet")
    rows = slice(None) if agents is None else agents
    return TeamView(observer.memory, observer.positions[:, rows], observer.walls, observer.team_mask[:, rows],
                    bool(noise) or observer.sensing.noise)


def team_scores(name: str, observer, noise: bool = False) -> torch.Tensor:
    """float32 [1,N,8]: controller ``name``'s move scores for every agent of the team, from
    ``observer``'s last observed step (-inf where a move is invalid)."""
    with torch.no_grad():
        return controller_scores(name, team_view(observer, noise))


def own_scores(name: str, observer, noise: bool = False) -> torch.Tensor:
    """float32 [8]: this agent's row (``observer.index``) of :func:`team_scores`. The classical
    controllers (gradient, greedy, infotaxis) decide each agent's move independently and row by row,
    so the row is computed alone (the team's other N - 1 rows, which this agent does not use, are
    not); a coordinated controller (``COORDINATED``: agents choose in turn) computes the rows of the
    agents before this one too, the same sequence every teammate computes from the same team state;
    the other information-driven searchers (``SEARCHERS``) place their count quadrature and keep
    their levels from the whole batch of rows they score, so the agent scores the whole team and
    takes its row: the move the batched core makes for it."""
    i = observer.index
    if name in COORDINATED:
        rows, own = slice(0, i + 1), -1
    elif name in SEARCHERS:
        rows, own = slice(None), i
    else:
        rows, own = slice(i, i + 1), -1
    with torch.no_grad():
        return controller_scores(name, team_view(observer, noise, rows))[0, own]


def controller_move(name: str, observer, mask: torch.Tensor | None = None, noise: bool = False) -> int:
    """This agent's move (an action index) under controller ``name``: the argmax of its own row
    (``observer.index``) of the team's scores (:func:`own_scores`), masked by ``mask`` bool [8]
    (default: the observer's own move mask) as a bundle's move is.

    Raises:
        ValueError: an unknown controller name. RuntimeError: no step observed yet.
    """
    scores = own_scores(name, observer, noise)
    if mask is None:
        mask = observer.team_mask[0, observer.index]
    return int(scores.masked_fill(~mask.to(torch.bool), float("-inf")).argmax())


def controller_scenario(name: str, agents: int, grid: int, application: str | None = APPLICATION) -> None:
    """Check that an agent can start with controller ``name``: the team size and grid must be given
    (a controller has no manifest to take them from) and the application must be target
    localization.

    Raises:
        ValueError: with what to pass instead.
    """
    if application and application != APPLICATION:
        raise ValueError(f"controller {name!r} plays {APPLICATION}, but this agent's application is "
                         f"{str(application)[:60]!r}")
    missing = [key for key, value in (("agents", agents), ("grid", grid)) if value < 1]
    if missing:
        given = " ".join(f"-p {key}:=<n>" for key in missing)
        raise ValueError(f"controller {name!r} has no manifest to take the team size and grid from: "
                         f"start the agent with {given}")
