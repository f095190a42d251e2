"""The catalogue the experiments draw on: phases, budgets per scale, the experts and users.

Everything here is data; :mod:`.figures` declares which runs each paper figure makes from it and
:mod:`.plan` turns those declarations into jobs.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from medc_training.envs.names import FLEET_COORDINATION, MAZE_CLEANING

PHASES = ("experts", "fig6", "fig7", "fig8", "fig9", "fig10", "long", "long-other", "sweep")

# Per-scale budget: training steps of each experiment run, of each expert, of the team.
BUDGETS = {
    "cpu": {"steps": 150_000, "expert_steps": 128_000, "team_steps": 128_000, "fleet_maze_steps": 300_000,
            "long_steps": 200_000},
    "paper": {"steps": 20_000_000, "expert_steps": 2_000_000, "team_steps": 2_000_000,
              "fleet_maze_steps": 20_000_000, "long_steps": 20_000_000},
    "claims": {"steps": 250_000, "expert_steps": 128_000, "team_steps": 128_000, "fleet_maze_steps": 0,
               "long_steps": 250_000},
}


@dataclass(frozen=True)
class Scope:
    """What a scale's reproduction covers: its seeds start at ``first_seed``; only the
    target-localization panels with ``walls`` obstructions (None: all) are run; ``team``: whether
    the shipped team is cloned with the experts; ``other_apps``: whether fleet coordination and
    maze cleaning are part of it; ``sweep``: whether the when-do-experts-help sweep
    (docs/reproduction/claims/SWEEP.md, phase "sweep") is planned: it is an amendment of the claims
    protocol alone, so any other scale plans no run of it."""

    first_seed: int = 0
    walls: tuple[int, ...] | None = None
    team: bool = True
    other_apps: bool = True
    sweep: bool = False
    #: The report's rules: seeds the learnability gate needs; random play's fixed episodes in the
    #: gate (None: the run's own evaluation episodes); the CI half-width above which a "not
    #: resolved" claim is also "under-powered" (None: no such label); the folder (under OUT) of the
    #: reference lines (:mod:`.references`; None: none); the protocol file the report includes.
    gate_min_seeds: int = 3
    gate_random_episodes: int | None = None
    underpowered: float | None = None
    reference: str | None = None
    protocol: str = "protocol.md"
    #: Seeds each side of a claim needs before it gets a verdict; with fewer it reads "incomplete"
    #: (the runs still under way of a pre-registered protocol; None: a verdict from what ran).
    claim_min_seeds: int | None = None
    #: The date of the analysis the report adds after its protocol's verdicts (paired by seed,
    #: power of the test used, non-inferiority by its bound, censored speed-ups, Holm;
    #: :mod:`.posthoc`), None: no such section; and the seed-to-seed SD the protocol planned its
    #: power with (None: it planned none).
    posthoc: str | None = None
    planning_sd: float | None = None


#: The date of the analysis added after the committed protocols (cpu and claims scales).
POSTHOC = "2026-12-03"

#: The claims protocol (docs/reproduction/claims/PROTOCOL.md): seeds 300-304, the A3W2 panels
#: only, its own experts and no shipped team, target localization only; the gate on 5 seeds against
#: random play on 256 fixed episodes; "under-powered" above a half-width of 5.9 steps; the classical
#: controllers as reference lines; a claim judged only once both sides have their 5 seeds; its
#: sweep amendment; power planned at a seed-to-seed SD of 3.4 steps.
SCOPES = {"cpu": Scope(posthoc=POSTHOC), "paper": Scope(),
          "claims": Scope(first_seed=300, walls=(2,), team=False, other_apps=False, sweep=True,
                          gate_min_seeds=5, gate_random_episodes=256, underpowered=5.9, reference="reference",
                          protocol="PROTOCOL.md", claim_min_seeds=5, posthoc=POSTHOC, planning_sd=3.4)}

# Target-localization experts: (name, agents, walls, architecture). The paper's 6 FRL/MEDC
# users A1W0, A3W0, A2W1, A2W2, A2W3, A3W1 plus the "complex" A1W3 of Fig. 6. Two
# architectures are mixed on purpose: MEDC only needs actions from its experts. On the default
# agent-centred observation with the source estimate an MLP clones the oracle well (on the
# paper's absolute maps it did not: A3W2, 51k steps of DAgger, greedy 33 steps against
# LeNet-5's 7, random 36), so the MLP is mixed with the paper's LeNet-5.
TL_EXPERTS = (
    ("A1W0", 1, 0, "mlp"),
    ("A1W3", 1, 3, "lenet5"),
    ("A3W0", 3, 0, "mlp"),
    ("A2W1", 2, 1, "lenet5"),
    ("A2W2", 2, 2, "mlp"),
    ("A2W3", 2, 3, "lenet5"),
    ("A3W1", 3, 1, "mlp"),
)
SIX = ("A1W0", "A3W0", "A2W1", "A2W2", "A2W3", "A3W1")        # paper Section V-C, first 6 users
PROPER5 = ("A1W0", "A3W0", "A2W1", "A2W2", "A3W1")            # Fig. 7 "proper experts"
FRL_USERS = ((1, 0), (3, 0), (2, 1), (2, 2), (2, 3), (3, 1), (3, 2), (3, 3))
FAULTY_USERS = {"A2W1": "random", "A2W2": "biased", "A3W1": "malicious"}  # Fig. 9: 3 of the 8

# The when-do-experts-help sweep (docs/reproduction/claims/SWEEP.md): MEDC with the six users'
# experts over area (grid side) x R_E at Q 0.05, and over Q at the protocol's area and R_E; MDRL-sparse
# at each area; 3 seeds. Reward gets rarer as the area grows at the protocol's fixed step limit.
SWEEP_GRIDS = (24, 32, 40)
SWEEP_RATES = (0.1, 0.3, 0.6)
SWEEP_QS = (0.01, 0.05, 0.2)
#: The protocol's own setting (grid, R_E, Q): its cell is Fig. 8's MEDC run, its sparse Fig. 6's.
SWEEP_PROTOCOL = (40, 0.1, 0.05)
SWEEP_SEEDS = 3
#: The Welch CI half-width 3 seeds per arm give at the probes' seed-to-seed SD of 3.4 steps
#: (4.30 x sqrt(2 x 3.4^2 / 3)): a cell whose CI is wider is labelled under-powered.
SWEEP_UNDERPOWERED = 11.9

# Fleet coordination and maze cleaning: the paper's 10x10 grid at every scale. The paper gives
# no step limit; 400 lets a uniformly random team finish some episodes (measured on 64
# episodes: maze complexity 1.0 42%, fleet with 8 customers 9%; at 100 steps neither ever
# finishes, and every curve sits flat at the limit). A memoryless greedy policy repeats one
# move forever in these coverage tasks, so they are evaluated on sampled actions: 32 fixed
# episodes over 16 environments (two rounds of at most 400 steps), or with the legacy window
# (eval_episodes 0, the committed reproduction) 16 environments x 400 steps per evaluation.
OTHER_GRID = 10
OTHER_MAX_STEPS = 400
OTHER_EVAL = {"eval_greedy": False, "eval_envs": 16, "eval_steps": 16 * OTHER_MAX_STEPS, "eval_episodes": 32}

# Fleet coordination / maze cleaning experts: (name, agents, env options); the user of
# interest is 3 agents (fleet: 8 customers; maze: complexity 1.0). "short" prefixes run names.
# The observation is an env option of these two applications: maze cleaning takes the
# agent-centred window `ego9` (the whole 10x10 grid re-centred on the agent), with which MDRL-sparse
# learns in 300k steps where the paper's absolute maps do not (docs/environments.md); fleet
# coordination keeps the paper's maps (it learns with neither in that budget).
MAZE_OBSERVATION = {"observation": "ego9"}
OTHER_APPS = {
    FLEET_COORDINATION: {
        "short": "fleet",
        "title": "Fleet coordination",
        "target": {"customers": 8},
        "experts": (("fleet-A1C4", 1, {"customers": 4}), ("fleet-A2C4", 2, {"customers": 4}),
                    ("fleet-A2C6", 2, {"customers": 6}), ("fleet-A1C8", 1, {"customers": 8}),
                    ("fleet-A3C4", 3, {"customers": 4}), ("fleet-A2C8", 2, {"customers": 8})),
    },
    MAZE_CLEANING: {
        "short": "maze",
        "title": "Maze cleaning",
        "target": {"complexity": 1.0, **MAZE_OBSERVATION},
        "experts": tuple((name, agents, {"complexity": c, **MAZE_OBSERVATION}) for name, agents, c in (
            ("maze-A1C0", 1, 0.0), ("maze-A2C0", 2, 0.0), ("maze-A1C1", 1, 1.0), ("maze-A2C1", 2, 1.0),
            ("maze-A3C0", 3, 0.0), ("maze-A2C05", 2, 0.5))),
    },
}


def tl_architectures() -> tuple[str, ...]:
    """The architectures mixed among the target-localization experts, in catalogue order."""
    return tuple(dict.fromkeys(arch for *_, arch in TL_EXPERTS))


def long_tag(steps: int) -> str:
    """Run-name prefix of a supplementary long run, e.g. long200k."""
    return f"long{steps // 1000}k" if steps % 1_000_000 else f"long{steps // 1_000_000}M"


def long_tags_on_disk(runs: Path, markers) -> list[str]:
    """The long_tag prefixes of the runs ``<tag>-<marker>`` under ``runs`` for any of ``markers``,
    shortest run first."""
    tags = {d.name[: -len(m) - 1] for m in markers for d in runs.glob(f"long*-{m}")}
    return sorted(tags, key=lambda t: float(t[4:-1]) * (1000 if t.endswith("k") else 1_000_000))
