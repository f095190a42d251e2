"""A run folder holds one configuration: what it records, and how a resume or
an "already done" check compares it.

A run is its :class:`~medc_training.config.TrainConfig` plus its *inputs*, what else its learner
was built from: the expert specs (paths or names) and their weights, and the FRL users whose own
curves it logs. ``summary.json`` (a finished run) and ``checkpoint.safetensors`` (a running one)
record both (``config``, ``inputs``). Every field is compared, except:

* ``torch_threads`` everywhere (how many CPU threads computed it, not what was computed);
* ``total_steps`` when resuming (a killed run may be carried on to another step count: the steps
  before are the same whatever the total).

A record written before inputs were recorded (the committed docs/reproduction runs) compares its
config only; a config recorded before a field existed reads as :meth:`TrainConfig.from_dict` says.
"""

from __future__ import annotations

import json
from typing import Any

#: Fields never compared: they do not change what a run computes.
PERFORMANCE_ONLY = ("torch_threads",)
#: Fields a resumed run may change.
RESUME_FREE = ("total_steps", *PERFORMANCE_ONLY)


class RunMismatch(ValueError):
    """A run folder holds another configuration than the one asked for; the message names every
    differing field and what to do."""


def run_inputs(experts=(), expert_weights=None, side_users=()) -> dict[str, Any]:
    """The inputs record of a run: expert specs, their weights (None: by the QoS rule), FRL side users."""
    return {"experts": [str(e) for e in experts or ()],
            "expert_weights": None if expert_weights is None else [float(w) for w in expert_weights],
            "side_users": [int(u) for u in side_users or ()]}


def job_inputs(job: dict) -> dict[str, Any]:
    """:func:`run_inputs` of an experiment job dict (medc_training.experiments.plan)."""
    return run_inputs(job.get("experts", ()), job.get("expert_weights"), job.get("side_users", ()))


def _plain(value: Any) -> Any:
    return json.loads(json.dumps(value, default=str))


def differences(recorded_config: dict, recorded_inputs: dict | None, config: dict, inputs: dict | None,
                ignore: tuple[str, ...] = PERFORMANCE_ONLY) -> list[str]:
    """``field=recorded vs wanted`` for every field that differs (sorted; empty when none).

    ``recorded_inputs`` None (recorded before inputs were) compares the config only.
    """
    from .config import TrainConfig

    try:
        old = _plain(TrainConfig.from_dict(recorded_config).to_dict())
    except (TypeError, ValueError) as exc:
        return [f"the recorded config cannot be read ({exc})"]
    new = _plain(TrainConfig.from_dict(config).to_dict())
    out = [f"{key}={old.get(key)!r} recorded vs {new.get(key)!r} now"
           for key in sorted(set(old) | set(new)) if key not in ignore and old.get(key) != new.get(key)]
    if recorded_inputs is not None and inputs is not None:
        a, b = _plain(recorded_inputs), _plain(inputs)
        out += [f"{key}={a.get(key)!r} recorded vs {b.get(key)!r} now"
                for key in sorted(set(a) | set(b)) if a.get(key) != b.get(key)]
    return out


def check_finished(summary: dict, config: dict, inputs: dict | None, where: str,
                   flag: str = "--overwrite") -> bool:
    """True when the finished run ``summary`` (its summary.json) is the run ``config`` + ``inputs``
    describe.

    Raises:
        RunMismatch: it is another run; the message names the differing fields and ``flag``.
    """
    diffs = differences(summary.get("config", {}), summary.get("inputs"), config, inputs)
    if diffs:
        raise RunMismatch(f"{where} holds a finished run of another configuration ({'; '.join(diffs)}); "
                          f"give {flag} to replace it, or use another output folder")
    return True
