"""A request for models, typed: what ``allocateModels`` is asked before its candidates.

:class:`ModelRequest` holds the six request arguments in the contract's units (features as
integers, weights and reputations in fixed point), checked; :func:`takes_request` gives a method
of the registry those six arguments, as the caller writes them, in one place.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from medc_training.envs.names import DEFAULT_APPLICATION
from medc_training.qos import fixed_weights, to_fixed

from .chain import ContractRevert

MAX_FEATURES = 8
#: Longest application name (UTF-8 bytes) shared or requested; checked before anything is sent.
MAX_APPLICATION_BYTES = 128
#: Most candidate models one allocateModels call examines (the contract's MAX_CANDIDATES).
MAX_CANDIDATES = 256
#: Most models one request may ask for (so a ranking page always has room for new candidates).
MAX_COUNT = MAX_CANDIDATES // 2
_UINT32 = 2**32 - 1

Features = Mapping[str, int] | Sequence[int]


@dataclass(frozen=True)
class ModelRequest:
    """A checked request for models of one application, in the contract's units."""

    application: str
    #: The requester's environment features E^r, in the application's order.
    requirements: tuple[int, ...]
    #: One fixed-point weight per feature summing to 1e18, or () for equal weights.
    weights: tuple[int, ...]
    count: int
    min_model_rep: int  # fixed point
    min_owner_rep: int  # fixed point

    @classmethod
    def build(
        cls,
        features_of: Callable[[str], tuple[str, ...] | None],
        application: str,
        requirements: Features,
        weights: Features | None = None,
        count: int = 1,
        min_model_rep: float = 0.0,
        min_owner_rep: float = 0.0,
    ) -> ModelRequest:
        """The request a caller's arguments describe (the one place they are written).

        ``features_of(application)``: the application's feature names (() when not named), None
        when no model of it was shared (then ``ContractRevert("UnknownApplication")``).
        """
        check_application(application)
        if isinstance(count, bool) or not isinstance(count, int) or not 1 <= count <= MAX_COUNT:
            raise ValueError(f"count must be an integer from 1 to {MAX_COUNT}, got {count!r}")
        req_names, req = parse_features(requirements)
        expected = features_of(application)
        if expected is None:
            raise ContractRevert("UnknownApplication", {"application": application})
        if req_names and expected and req_names != expected:
            raise ValueError(f"{application!r} models use features {list(expected)}, got {list(req_names)}")
        w: list[int] = []
        if weights is not None:
            w_names, w_raw = _parse_weights(weights)
            if w_names and req_names and w_names != req_names:
                raise ValueError(f"weights name {list(w_names)}, requirements name {list(req_names)}")
            if len(w_raw) != len(req):
                raise ValueError(f"give one weight per feature ({len(req)}), got {len(w_raw)}")
            w = w_raw
        return cls(
            application,
            tuple(req),
            tuple(w),
            count,
            to_fixed(min_model_rep, "min_model_rep"),
            to_fixed(min_owner_rep, "min_owner_rep"),
        )

    def args(self) -> list[Any]:
        """The request's arguments of ``allocateModels``, in order, as JSON-able lists."""
        return [
            self.application,
            list(self.requirements),
            list(self.weights),
            self.count,
            self.min_model_rep,
            self.min_owner_rep,
        ]


#: What a caller passes for a request: :meth:`ModelRequest.build` less its ``features_of``.
REQUEST_PARAMETERS = tuple(inspect.signature(ModelRequest.build).parameters.values())[1:]


def takes_request(method: Callable[..., Any]) -> Callable[..., Any]:
    """Let ``method(self, request: ModelRequest, **rest)`` be called with the request's arguments
    (those of :meth:`ModelRequest.build` after ``features_of``) followed by its own ``rest``; the
    request is built with ``self.feature_names`` as ``features_of``."""
    own_signature = inspect.signature(method)
    own = list(own_signature.parameters.values())
    signature = inspect.Signature(
        [own[0], *REQUEST_PARAMETERS, *own[2:]], return_annotation=own_signature.return_annotation
    )
    names = [p.name for p in REQUEST_PARAMETERS]

    @functools.wraps(method)
    def wrapper(self: Any, *args: Any, **kwargs: Any) -> Any:
        bound = signature.bind(self, *args, **kwargs)
        bound.apply_defaults()
        given = dict(bound.arguments)
        del given[own[0].name]
        request = ModelRequest.build(self.feature_names, **{n: given.pop(n) for n in names})
        return method(self, request, **given)

    wrapper.__signature__ = signature  # type: ignore[attr-defined]
    return wrapper


def request_id_from(value: str | bytes | None) -> bytes:
    """A 32-byte request id: ``0x`` + 64 hex digits as is, other text hashed, None a random one."""
    if value is None:
        return os.urandom(32)
    if isinstance(value, bytes | bytearray):
        if len(value) != 32:
            raise ValueError(f"a request id given as bytes must be 32 bytes, got {len(value)}")
        rid = bytes(value)
    elif isinstance(value, str) and value.strip():
        text = value.strip()
        if text.lower().startswith("0x") and len(text) == 66:
            try:
                rid = bytes.fromhex(text[2:])
            except ValueError:
                raise ValueError(f"request id {value!r} is not 0x + 64 hex digits") from None
        else:
            rid = hashlib.sha256(text.encode()).digest()
    else:
        raise ValueError(f"a request id must be a non-empty string or 32 bytes, got {value!r}")
    if rid == bytes(32):
        raise ValueError("the request id must not be zero")
    return rid


def check_application(application: str) -> None:
    """Refuse an application name that is not a non-empty string of at most
    :data:`MAX_APPLICATION_BYTES` bytes of UTF-8 without control characters."""
    if not isinstance(application, str) or not application.strip():
        raise ValueError(f"application must be a non-empty string, e.g. {DEFAULT_APPLICATION!r}")
    try:
        size = len(application.encode("utf-8"))
    except UnicodeEncodeError:
        raise ValueError("application must be valid Unicode text (no lone surrogates)") from None
    if size > MAX_APPLICATION_BYTES:
        raise ValueError(f"application is {size} bytes, over the {MAX_APPLICATION_BYTES} byte limit "
                         f"(a name such as {DEFAULT_APPLICATION!r})")
    if any(ord(ch) < 32 or 127 <= ord(ch) < 160 for ch in application):
        raise ValueError(f"application must not hold control characters (e.g. {DEFAULT_APPLICATION!r})")


def parse_features(features: Features) -> tuple[tuple[str, ...], list[int]]:
    """(names in sorted order, or () for a sequence; the values in that order), checked."""
    if isinstance(features, Mapping):
        names = tuple(sorted(features))
        values = [features[n] for n in names]
    elif isinstance(features, Sequence) and not isinstance(features, str | bytes):
        names, values = (), list(features)
    else:
        raise ValueError("environment features must be a mapping name -> int or a sequence of ints")
    if len(values) > MAX_FEATURES:
        raise ValueError(f"at most {MAX_FEATURES} environment features, got {len(values)}")
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int) or not 0 <= v <= _UINT32:
            raise ValueError(f"environment feature values must be integers in [0, {_UINT32}], got {v!r}")
    return names, [int(v) for v in values]


def _parse_weights(weights: Features) -> tuple[tuple[str, ...], list[int]]:
    if isinstance(weights, Mapping):
        names = tuple(sorted(weights))
        raw = [weights[n] for n in names]
    else:
        names, raw = (), list(weights)
    return names, fixed_weights(raw)
