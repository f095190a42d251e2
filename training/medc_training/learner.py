"""The learner protocol: what the run loop (:func:`medc_training.runner.run_training`) drives.

Two classes implement it: :class:`medc_training.ppo.Trainer` (one learner) and
:class:`medc_training.frl.FederatedGroup` (U Trainers averaged by FedAvg). The run loop needs
nothing else from a learner, so a new kind of learner implements these members and runs.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

if TYPE_CHECKING:
    from .ppo import Trainer


@runtime_checkable
class Learner(Protocol):
    """One training run's learner, as the run loop sees it."""

    @property
    def global_step(self) -> int:
        """Training steps taken so far (of the focal learner)."""
        ...

    @property
    def focal(self) -> Trainer:
        """The Trainer whose policy is evaluated, whose training statistics are logged and which is
        shipped as the run's bundle."""
        ...

    def train_update(self) -> dict:
        """Collect and learn from one rollout; returns the update's losses."""
        ...

    def evaluate(self) -> dict:
        """The focal policy's test play (:meth:`medc_training.ppo.Trainer.evaluate`)."""
        ...

    def side_names(self) -> list[str]:
        """Names of the other learners whose evaluation curves the run loop also records."""
        ...

    def side_evaluate(self) -> dict[str, dict]:
        """Evaluation of each of :meth:`side_names`, by name."""
        ...

    def state_dict(self) -> dict:
        """Everything needed to resume (the run loop checkpoints it after every update)."""
        ...

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (``--resume``)."""
        ...


def check_learner(learner: object) -> Learner:
    """Return ``learner`` if it implements :class:`Learner`; otherwise raise TypeError naming what
    it lacks."""
    if not isinstance(learner, Learner):
        missing = [m for m in vars(Learner) if not m.startswith("_") and not hasattr(learner, m)]
        raise TypeError(f"{type(learner).__name__} is not a learner: it lacks {', '.join(missing)} "
                        "(use a medc_training.ppo.Trainer or a medc_training.frl.FederatedGroup)")
    return learner
