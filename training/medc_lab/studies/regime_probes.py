"""Regime probes for the claims protocol: where is reward rare, and how good are the classical controllers?

Step 1 of the claims protocol (docs/reproduction/claims/PROTOCOL.md) chooses the regime before any
MEDC run, from random play, the classical controllers and MDRL-sparse only. This module plays the
first part: random moves and the classical controllers (:mod:`medc_training.controllers`) on the
candidate regimes of the realistic sensing preset, each policy on the same fixed episodes played to
their end (:func:`medc_training.evaluate.play_episodes`). Sparse's probes are ordinary ``medc-train``
runs (``scripts/claims_probes.sh``).

``python -m medc_lab.cli.regimes play --out docs/reproduction/claims/probes``
plays what is missing (one JSON per regime and policy; finished ones are skipped, so it resumes);
``report`` prints the table (success rate and mean episode length with 95% CIs).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from medc_training.stats import mean_ci


@dataclass(frozen=True)
class Regime:
    """A candidate regime: the grid side, the walls and the step limit of its episodes."""

    grid: int
    walls: int
    max_steps: int

    @property
    def name(self) -> str:
        return f"g{self.grid}w{self.walls}t{self.max_steps}"


AGENTS = 3
EPISODES = 256
EVAL_SEED = 20261203
POLICIES = ("random", "gradient", "greedy", "infotaxis")

#: The candidates: the study's 30x30 (random play succeeds in ~30% of its episodes), shorter
#: episodes on it, and larger areas up to the estimator's pair-table limit (48 cells a side).
REGIMES = (
    Regime(30, 2, 100), Regime(30, 2, 60), Regime(30, 5, 60),
    Regime(40, 2, 100), Regime(40, 2, 70), Regime(40, 2, 50), Regime(40, 5, 100), Regime(48, 2, 100),
    Regime(48, 2, 70),
)


def parse_regime(text: str) -> Regime:
    """'g40w2t100' -> Regime(40, 2, 100)."""
    try:
        grid, rest = text.removeprefix("g").split("w", 1)
        walls, steps = rest.split("t", 1)
        return Regime(int(grid), int(walls), int(steps))
    except ValueError:
        raise ValueError(f"regime {text[:40]!r}: write it as g<grid>w<walls>t<max steps>, "
                         "e.g. g40w2t100") from None


def play(regime: Regime, policy: str, episodes: int = EPISODES, eval_seed: int = EVAL_SEED) -> dict:
    """Play ``policy`` on the regime's ``episodes`` fixed episodes of ``eval_seed``; the per-episode
    results and their summary."""
    from medc_training.controllers import controller_policy
    from medc_training.envs import make_batched
    from medc_training.envs.names import TARGET_LOCALIZATION
    from medc_training.evaluate import play_episodes

    env = make_batched(TARGET_LOCALIZATION, num_envs=episodes, seed=eval_seed, agents=AGENTS,
                       walls=regime.walls, grid=regime.grid, max_steps=regime.max_steps, sensing="realistic",
                       posterior=policy != "random", copy_obs=False, observation="maps")
    start = time.perf_counter()
    net = None if policy == "random" else controller_policy(policy, env)
    played = play_episodes(env, net, episodes=episodes, seed=eval_seed)
    lengths = [float(x) for x in played.lengths]
    successes = [float(bool(x)) for x in played.successes]
    return {"regime": regime.name, "policy": policy, "grid": regime.grid, "walls": regime.walls,
            "max_steps": regime.max_steps, "agents": AGENTS, "sensing": "realistic", "episodes": episodes,
            "eval_seed": eval_seed, "seconds": round(time.perf_counter() - start, 1),
            "lengths": lengths, "successes": successes}


def summary(record: dict) -> dict:
    """Mean episode length and success rate with 95% CIs."""
    length, length_ci = mean_ci(record["lengths"])
    success, success_ci = mean_ci(record["successes"])
    return {"length": length, "length_ci": length_ci, "success": success, "success_ci": success_ci}
