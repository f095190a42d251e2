"""QoS and D_m as the Models Manager contract computes them, once, for every Python user.

``contracts/src/ModelsManager.sol`` works in fixed point (:data:`ONE` = 10**18 = 1.0); this module
states its rules on the same integers, so the registry client, the trainer's R_S and the demo agree
with the chain to the last digit (``tests/registry/test_qos_mirror.py`` checks it against the
deployed contract). D_m, QoS, the ranking of exact matches (:func:`rank_key`), R_S
(:func:`selection_weights`) and the training-side experts' features: docs/registry.md
("Contracts") and docs/training.md ("The methods"). Pure Python: no torch, web3 or ROS.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from fractions import Fraction
from numbers import Real

#: Fixed-point one (1.0), the contract's ONE.
ONE = 10**18
#: Reputation of a new user and of a model not reviewed yet (0.5), the contracts' INITIAL_REPUTATION.
INITIAL_REPUTATION = ONE // 2
#: The QoS the contract's ModelAllocated event reports for an exact match (D_m = 0).
QOS_EXACT = 2**256 - 1
#: The top bit of the contract's ranking key marks an exact match.
_EXACT_BIT = 1 << 255


def to_fixed(value: float, name: str = "value") -> int:
    """A float in [0, 1] as fixed point (1e18 = 1.0), e.g. a review or a minimum reputation."""
    v = float(value)
    if not (math.isfinite(v) and 0.0 <= v <= 1.0):
        raise ValueError(f"{name} must be between 0 and 1, got {value!r}")
    return round(v * ONE)


def from_fixed(value: int) -> float:
    """Fixed point (1e18 = 1.0) as a float."""
    return value / ONE


def fixed_weights(weights: Sequence[float]) -> list[int]:
    """Feature weights w_i (non-negative floats summing to 1) as the contract takes them: fixed
    point, the rounding absorbed by the last weight so that the sum is exactly ONE."""
    raw = [float(w) for w in weights]
    if not raw or any(not math.isfinite(w) or w < 0 for w in raw):
        raise ValueError(f"weights must be non-negative numbers, got {raw!r}")
    total = sum(raw)
    if total <= 0 or abs(total - 1.0) > 1e-9:
        raise ValueError(f"weights must sum to 1, got {total}")
    fixed = [round(w * ONE) for w in raw]
    fixed[-1] += ONE - sum(fixed)
    if fixed[-1] < 0:
        raise ValueError("weights must sum to 1")
    return fixed


def _number(value, what: str) -> Fraction | int:
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value):
        raise ValueError(f"{what} must be a finite number, got {value!r}")
    return value if isinstance(value, int) else Fraction(value)


def distance(env: Sequence[Real], requirements: Sequence[Real], weights: Sequence[int] | None = None) -> int:
    """D_m in fixed point (ONE = one feature unit), as ``ModelsManager._distance``.

    ``weights``: None (or empty) for equal weights, else fixed-point w_i, one per feature,
    summing to exactly ONE (the contract reverts with InvalidWeights otherwise; this raises).
    """
    if len(env) != len(requirements):
        raise ValueError(f"the model has {len(env)} features, the requirements {len(requirements)}")
    diffs = [abs(_number(a, "a feature") - _number(b, "a feature")) for a, b in zip(env, requirements)]
    p = len(diffs)
    if not weights:
        return 0 if p == 0 else int(sum(diffs) * ONE // p)
    if len(weights) != p or sum(weights) != ONE or any(
            isinstance(w, bool) or not isinstance(w, int) or w < 0 for w in weights):
        raise ValueError(f"weights must be {p} non-negative fixed-point integers summing to {ONE}, "
                         f"got {list(weights)!r}")
    return int(sum(w * d for w, d in zip(weights, diffs)) // 1)


def rep_product(owner_rep: int = INITIAL_REPUTATION, model_rep: int = INITIAL_REPUTATION) -> int:
    """Rep_owner · Rep_model in fixed point (rounded down, as the contract)."""
    return owner_rep * model_rep // ONE


def qos(dist: int, owner_rep: int = INITIAL_REPUTATION, model_rep: int = INITIAL_REPUTATION) -> int:
    """QoS_m in fixed point as the contract reports it: Rep_owner·Rep_model / D_m, or
    :data:`QOS_EXACT` for an exact match (D_m = 0)."""
    if dist == 0:
        return QOS_EXACT
    return rep_product(owner_rep, model_rep) * ONE // dist


def rank_key(dist: int, owner_rep: int = INITIAL_REPUTATION, model_rep: int = INITIAL_REPUTATION) -> int:
    """The contract's ranking key: QoS_m, or for D_m = 0 the top bit over the rep product, so that
    exact matches outrank every finite QoS (higher is better; ties go to the lower model id)."""
    if dist == 0:
        return _EXACT_BIT | rep_product(owner_rep, model_rep)
    return qos(dist, owner_rep, model_rep)


def is_exact(qos_value: float | int) -> bool:
    """Whether a QoS value (fixed point, or float as the registry client gives it) is an exact match."""
    return qos_value == QOS_EXACT or qos_value == math.inf


def selection_weights(qos_values: Sequence[float | int],
                      rep_products: Sequence[float | int] | None = None) -> list[float]:
    """R_S_i = QoS_i / Σ_j QoS_j, the roulette wheel's slices (floats summing to 1).

    ``qos_values`` are fixed-point ints (:data:`QOS_EXACT` for D_m = 0) or floats as the registry
    client reports them (``math.inf`` for D_m = 0). If any is an exact match, the exact matches
    share the wheel in proportion to ``rep_products`` (Rep_owner·Rep_model of each expert, in any
    one unit; None = equal) and the others get 0 (see the module docstring).
    """
    values = list(qos_values)
    if not values:
        raise ValueError("R_S needs at least one QoS value")
    exact = [is_exact(q) for q in values]
    if any(exact):
        reps = list(rep_products) if rep_products is not None else [1] * len(values)
        if len(reps) != len(values):
            raise ValueError(f"give one rep product per QoS value ({len(values)}), got {len(reps)}")
        values = [r if e else 0 for r, e in zip(reps, exact)]
    for v in values:
        if isinstance(v, bool) or not isinstance(v, Real) or not math.isfinite(v) or v < 0:
            raise ValueError(f"QoS values and rep products must be finite and >= 0, got {v!r}")
    total = sum(values)
    if total <= 0:
        raise ValueError("every expert has QoS 0 (reputation 0): R_S is undefined; give the weights "
                         "explicitly")
    return [v / total for v in values]


def attribute_features(expert_attrs: Mapping | None, target_attrs: Mapping
                       ) -> tuple[list[Real], list[Real]]:
    """(E^m, E^r): the numeric attributes both sides name, in sorted name order."""
    def numeric(x) -> bool:
        return isinstance(x, Real) and not isinstance(x, bool)

    keys = sorted(k for k in set(expert_attrs or {}) & set(target_attrs)
                  if numeric(expert_attrs[k]) and numeric(target_attrs[k]))
    return [expert_attrs[k] for k in keys], [target_attrs[k] for k in keys]


def attribute_distance(expert_attrs: Mapping | None, target_attrs: Mapping) -> int:
    """D_m (fixed point, equal weights) of an expert described by an attribute dict, for a target.

    An expert that shares no numeric attribute with the target counts as the nearest inexact
    match: one unit off in one of the target's p numeric attributes, D_m = ONE // p.
    """
    env, req = attribute_features(expert_attrs, target_attrs)
    if env:
        return distance(env, req)
    _, own = attribute_features(target_attrs, target_attrs)
    return ONE // max(len(own), 1)


def expert_weights_from_attributes(expert_attrs: Sequence[Mapping | None], target_attrs: Mapping
                                   ) -> list[float]:
    """R_S of experts described by attribute dicts, with the initial reputations (0.5 each)."""
    return selection_weights([qos(attribute_distance(a, target_attrs)) for a in expert_attrs],
                             [rep_product()] * len(expert_attrs))


def normalised_weights(weights: Sequence[float], count: int) -> list[float]:
    """Explicit expert weights checked and normalised to sum 1: ``count`` of them (one per expert),
    finite, non-negative, with a positive sum."""
    values = list(weights)
    if len(values) != count:
        raise ValueError(f"give one expert weight per expert ({count}), got {len(values)}")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, Real) or not math.isfinite(v) or v < 0:
            raise ValueError(f"expert weights must be finite numbers >= 0, got {values!r}")
    if not values:
        return []
    total = math.fsum(values)
    if total <= 0:
        raise ValueError(f"expert weights must not all be 0, got {values!r}")
    return [float(v) / total for v in values]
