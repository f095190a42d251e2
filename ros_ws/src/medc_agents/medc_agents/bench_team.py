"""What an agent changes to play the field benchmark's world (no ROS here): the team's sensor model
and the classical endgame.

In the ``radbench`` world (``medc_training.radbench``) the team's estimator is the model a bundle
trained there was trained with: :func:`~medc_training.radbench.physics.team_sensing` under the
background prior its manifest records (``medc_training.bundle.manifest_prior``), or under the one
given as ``prior_background`` (``"LOW,HIGH,LEVELS"``, as ``medc-radbench --prior-background`` takes
it), not the realistic preset's own. Its obstructions are solid rectangles that may touch: the
memory takes the map's cover (``medc_training.envs.wall_cover``).

The classical endgame (``medc_training.radbench.endgame``): once the team's posterior holds at least
``endgame_tau`` of its mass on one cell and this agent can reach that cell's success region, its
move is the shortest-path move there (the planner's own costs, :func:`~medc_training.radbench.
endgame.planned_costs`, and the evaluator's greedy choice over them: the move ``medc-radbench
--endgame TAU`` makes on the same state); otherwise the policy's.
"""

from __future__ import annotations

import torch

#: The worlds an agent plays: the grid world and the field benchmark's.
WORLDS: tuple[str, ...] = ("grid", "radbench")
#: The sensing preset whose name the benchmark's team model carries.
RADBENCH_SENSING = "realistic"


def check_world(world: object) -> str:
    """``world`` if it is one of :data:`WORLDS`; ValueError naming them."""
    if world not in WORLDS:
        raise ValueError(f"world must be one of {', '.join(WORLDS)}, got {str(world)[:40]!r}")
    return str(world)


def check_endgame_tau(tau: object) -> float:
    """``tau`` as a float in (0, 1] (1: never plan); ValueError naming the parameter otherwise."""
    from medc_training.radbench.endgame import check_tau

    return check_tau(tau, "endgame_tau")


def team_model(world: str, sensing: str, prior_background: str, policy: str):
    """The team's sensor model in ``world``: the preset ``sensing`` (its name) in the grid world; in
    the benchmark's world, the benchmark's team model under ``prior_background`` ("LOW,HIGH,LEVELS")
    or, when that is empty, under the prior the manifest of the bundle at ``policy`` records (a
    controller's name: none), as a ``SensingModel`` named ``realistic``.

    Raises:
        ValueError: a prior in the grid world, another preset than ``realistic`` in the benchmark's,
        or a malformed prior, saying what to set.
    """
    from medc_training.radbench.physics import team_sensing

    check_world(world)
    given = str(prior_background or "").strip()
    if world == "grid":
        if given:
            raise ValueError("prior_background weighs the benchmark world's team model: it applies with "
                             "world radbench only; leave it empty in the grid world")
        return sensing
    if sensing != RADBENCH_SENSING:
        raise ValueError(f"the radbench world's team model is the {RADBENCH_SENSING} preset's; set sensing "
                         f"{RADBENCH_SENSING} (got {str(sensing)[:40]!r})")
    if given:
        try:
            return team_sensing(given)
        except ValueError as exc:
            raise ValueError(f"prior_background: {exc}") from None
    return team_sensing(_bundle_prior(policy))


def _bundle_prior(policy: str):
    """The background prior the manifest of the bundle at ``policy`` records (None: none, or no
    bundle: a controller's name or nothing). An unreadable bundle is left to the policy's own load,
    which refuses it with the reason."""
    from medc_agents.controller import controller_name
    from medc_agents.policy_slot import PolicyRejected, read_policy_manifest

    if not policy or controller_name(policy) is not None:
        return None
    from medc_training.bundle import BundleError, manifest_prior

    try:
        return manifest_prior(read_policy_manifest(policy))
    except (PolicyRejected, BundleError):
        return None


def model_words(sensing) -> str:
    """How a log line names the team's model: the preset's name, with the background prior where
    the benchmark's team model weighs one (``realistic (benchmark team model, background 10-50
    counts/s at 16 levels)``)."""
    from medc_training.envs.tl_sensing import parse_sensing
    from medc_training.radbench.physics import TEAM_SENSING

    model = parse_sensing(sensing)
    if isinstance(sensing, str) or model.strength != TEAM_SENSING.strength:
        return model.name
    return (f"{model.name} (benchmark team model, background {model.background[0]:g}-{model.background[1]:g} "
            f"counts/s at {model.levels[1]} levels)")


def endgame_move(observer, tau: float, mask: torch.Tensor) -> int | None:
    """This agent's endgame move on its team state (``observer``: a TeamObserver after
    ``observe()``), or None when the endgame does not plan it: ``tau`` >= 1, the posterior's mode holds
    less than ``tau``, or this agent cannot reach the mode's success region. ``mask`` bool [8]: this
    agent's move mask. The move is :func:`medc_training.radbench.endgame.agent_move`'s: the first
    allowed move with the fewest moves left."""
    from medc_training.radbench.endgame import agent_move

    return agent_move(observer.memory.posterior(), observer.walls, observer.positions, observer.sensing, tau,
                      observer.index, mask)
