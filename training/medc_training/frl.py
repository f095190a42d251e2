"""FRL baseline: U users, each with its own PPO learner on its own environment, FedAvg every K.

Every user runs the ordinary :class:`medc_training.ppo.Trainer` (method ``sparse``) on its
environment variant (e.g. the paper's A1W0, A3W0, A2W1, A2W2, A2W3, A3W1, A3W2, A3W3). After
every K updates of all users, the users' parameters are averaged (:func:`fedavg`) and the
global model is loaded back into every user, which carries on training (its optimiser state
is kept). The curve reported is the *focal* user's (the one whose environment is the run's).

Faulty users (paper Fig. 9): a user with ``fault`` set shares poisoned parameters instead of
its own:

- ``random``: a freshly initialised network each round (it contributes noise);
- ``biased``: its own network with the policy head rewired to always prefer one action
  (weights zeroed, bias +10 on action 0);
- ``malicious``: its own network with the policy head negated, so the moves it rates best
  become the ones it rates worst.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from .config import TrainConfig
from .fedavg import fedavg
from .nets import make_actor_critic
from .ppo import EVAL_SEED_OFFSET, Trainer

FAULTS = ("random", "biased", "malicious")

# The paper's 8 FRL users (Section V-C): (agents, walls).
PAPER_USERS = ((1, 0), (3, 0), (2, 1), (2, 2), (2, 3), (3, 1), (3, 2), (3, 3))


def poisoned_parameters(kind: str, state: dict[str, torch.Tensor], trainer: Trainer
                        ) -> dict[str, torch.Tensor]:
    """The parameters a faulty user shares instead of its own (see the module docstring)."""
    if kind not in FAULTS:
        raise ValueError(f"fault must be one of {FAULTS}, got {kind!r}")
    if kind == "random":
        fresh = make_actor_critic(trainer.cfg.arch, trainer.obs_shape, trainer.A)
        return {k: v.to(state[k].device) for k, v in fresh.state_dict().items()}
    out = {k: v.clone() for k, v in state.items()}
    if kind == "biased":
        out["policy.weight"].zero_()
        out["policy.bias"].zero_()
        out["policy.bias"][0] = 10.0
    else:
        out["policy.weight"].neg_()
        out["policy.bias"].neg_()
    return out


class FederatedGroup:
    """U Trainers trained in lock-step with FedAvg every ``every`` updates (a
    :class:`medc_training.learner.Learner`, as Trainer is)."""

    def __init__(self, cfg: TrainConfig, users: Sequence[dict] | None = None,
                 side_users: Sequence[int] = ()) -> None:
        users = list(users if users is not None else (cfg.frl_users or
                     [{"agents": a, "walls": w} for a, w in PAPER_USERS]))
        if not users:
            raise ValueError("FRL needs at least one user")
        self.cfg = cfg
        self.every = cfg.frl_every
        self.trainers: list[Trainer] = []
        self.faults: list[str | None] = []
        focal_index = None
        for i, user in enumerate(users):
            user = dict(user)
            fault = user.pop("fault", None)
            if fault is not None and fault not in FAULTS:
                raise ValueError(f"FRL user {i}: fault must be one of {FAULTS}, got {fault!r}")
            unknown = set(user) - {"agents", "walls", "env_options"}
            if unknown:
                raise ValueError(f"FRL user {i}: unknown keys {sorted(unknown)}; allowed: agents, walls, "
                                 "env_options, fault")
            ucfg = TrainConfig(**{**cfg.to_dict(), "method": "sparse", "frl_users": [],
                                  "agents": user.get("agents", cfg.agents),
                                  "walls": user.get("walls", cfg.walls),
                                  "env_options": user.get("env_options", cfg.env_options),
                                  "seed": cfg.seed + 101 * i})
            trainer = Trainer(ucfg)
            trainer.eval_seed = cfg.seed + EVAL_SEED_OFFSET  # the same test episodes as a single learner
            self.trainers.append(trainer)
            self.faults.append(fault)
            same_env = (ucfg.agents, ucfg.walls, ucfg.env_options) == (cfg.agents, cfg.walls, cfg.env_options)
            if focal_index is None and fault is None and same_env:
                focal_index = i
        if focal_index is None:
            raise ValueError(f"FRL: no honest user has this run's environment (agents={cfg.agents}, "
                             f"walls={cfg.walls}); add it to the users")
        self.focal_index = focal_index
        shapes = {t.obs_shape for t in self.trainers}
        if len(shapes) != 1:
            raise ValueError(f"FRL users must share one observation shape to average models, got {shapes}")
        for i in side_users:
            if not 0 <= i < len(self.trainers) or i == focal_index:
                raise ValueError(f"FRL side user {i} must be another user's index "
                                 f"(0..{len(self.trainers) - 1})")
        self.side_users = list(side_users)
        self.average()  # every user starts from the same global model, as in FedAvg

    @property
    def focal(self) -> Trainer:
        return self.trainers[self.focal_index]

    @property
    def global_step(self) -> int:
        """Training steps of the focal user (each user trains this many)."""
        return self.focal.global_step

    def user_name(self, i: int) -> str:
        """AyWz for users of an application with walls (target localization), ``user<i>`` otherwise."""
        from .envs import core_options

        c = self.trainers[i].cfg
        return f"A{c.agents}W{c.walls}" if "walls" in core_options(c.env) else f"user{i}"

    def evaluate(self) -> dict:
        """The focal user's evaluation (see Trainer.evaluate)."""
        return self.focal.evaluate()

    def side_names(self) -> list[str]:
        """Names of the extra users whose evaluation curves the run loop records."""
        return [self.user_name(i) for i in self.side_users]

    def side_evaluate(self) -> dict[str, dict]:
        """Greedy evaluation of each side user (see Trainer.evaluate)."""
        return {self.user_name(i): self.trainers[i].evaluate() for i in self.side_users}

    def average(self) -> None:
        """FedAvg the shared parameters and load the global model into every user."""
        shared = []
        for trainer, fault in zip(self.trainers, self.faults):
            state = trainer.net.state_dict()
            shared.append(poisoned_parameters(fault, state, trainer) if fault else state)
        merged = fedavg(shared)
        for trainer in self.trainers:
            trainer.net.load_state_dict(merged)

    def train_update(self) -> dict:
        """One update of every user; FedAvg every ``every`` updates. Returns the focal losses."""
        losses = {}
        for i, trainer in enumerate(self.trainers):
            result = trainer.train_update()
            if i == self.focal_index:
                losses = result
        if self.focal.updates % self.every == 0:
            self.average()
        return losses

    def state_dict(self) -> dict:
        return {"users": [t.state_dict() for t in self.trainers]}

    def load_state_dict(self, state: dict) -> None:
        if len(state["users"]) != len(self.trainers):
            raise ValueError(f"checkpoint has {len(state['users'])} FRL users, this run {len(self.trainers)}")
        for trainer, s in zip(self.trainers, state["users"]):
            trainer.load_state_dict(s)
