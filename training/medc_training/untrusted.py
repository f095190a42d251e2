"""What every reader of data from strangers shares: the bundle size ceiling, the text filter and
the bounded JSON reader.

Torch-free, so the registry (which fetches and caches bundles and parses JSON from the graph and
the chain), the agents (which load bundles) and the bundle loader itself import one value and one
helper instead of keeping copies in step.
"""

from __future__ import annotations

import json
import math
import re
from typing import Any

import numpy as np

#: The largest policy bundle anything in MEDC fetches, caches or loads: the bundle loader's file
#: ceiling, the registry's content limit (``medc_registry.cid.MAX_CONTENT_BYTES``) and the agents'
#: check. A shipped bundle is 0.1-2.4 MB; the largest architecture the caps allow is far below this.
MAX_BUNDLE_BYTES = 256 << 20


def printable(text: str, limit: int, drop: str = "") -> str:
    """``text`` with anything but printable ASCII (and any character in ``drop``, e.g. quotes)
    shown as ``?``, cut to ``limit`` characters with ``...`` marking a cut: safe to put in a
    message, a log line or on a terminal whatever a file or a topic message held."""
    clean = "".join(ch if " " <= ch <= "~" and ch not in drop else "?" for ch in text[:limit + 1])
    return clean if len(clean) <= limit else clean[:limit] + "..."


# ---------------------------------------------------------------- bounded JSON
#: Limits of :func:`parse_json` (the bundle manifests' reader and the registry bridge's): the
#: shipped manifests nest 4 levels deep and hold no string over 120 characters.
MAX_JSON_DEPTH = 16  # nested objects/lists; checked by a scan before json.loads ever recurses
MAX_STRING_CHARS = 4096  # any key or string value
MAX_NUMBER_CHARS = 40  # any JSON number literal (a 64-bit seed has 20 digits)


class UntrustedJSONError(ValueError):
    """A JSON text refused by :func:`parse_json`; the message names the limit, never the text."""


class _JSONLimit(ValueError):
    """A JSON text over one of the limits (the message names the limit, not the text)."""


# A JSON string literal (possessive: linear time on any input). Removing them leaves the brackets
# that structure the text, so nesting depth is measured without recursing.
_JSON_STRING = re.compile(r'"(?:[^"\\]++|\\.)*+"', re.S)
_NOT_BRACKET = re.compile(r"[^\[\]{}]++")


def json_depth(text: str) -> int:
    """How deep the objects and lists of a JSON text nest, by a linear scan (no parsing, no recursion).

    Brackets inside complete string literals do not count; those of an unterminated string do
    (such a text is not JSON anyway), so the result is never below the true depth.
    """
    brackets = _NOT_BRACKET.sub("", _JSON_STRING.sub("", text)).encode("ascii")
    if not brackets:
        return 0
    codes = np.frombuffer(brackets, dtype=np.uint8)
    steps = np.where((codes == ord("[")) | (codes == ord("{")), 1, -1)
    return int(np.cumsum(steps).max())


def _no_duplicates(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    # Two entries with one name would let a reader and a checker see different values.
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise _JSONLimit("a key appears twice in one object")  # which key is not said: file content
        out[key] = value
    return out


def _reject_constant(name: str) -> Any:
    raise _JSONLimit(f"non-standard JSON constant {name}")


def _parse_number(kind: type) -> Any:
    def parse(text: str) -> Any:
        if len(text) > MAX_NUMBER_CHARS:
            raise _JSONLimit(f"a number of more than {MAX_NUMBER_CHARS} characters")
        value = kind(text)
        if not math.isfinite(value):
            raise _JSONLimit("a number too large for a float")
        return value
    return parse


def _check_strings(value: Any, what: str, max_string: int) -> None:
    """Every key and string in ``value`` (depth already bounded) is valid Unicode and not over-long."""
    stack = [value]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            stack.extend(item.keys())
            stack.extend(item.values())
        elif isinstance(item, list):
            stack.extend(item)
        elif isinstance(item, str):
            if len(item) > max_string:
                raise UntrustedJSONError(f"{what} holds a string of more than {max_string} characters")
            try:
                item.encode("utf-8")
            except UnicodeEncodeError:
                raise UntrustedJSONError(f"{what} holds invalid Unicode (a lone surrogate, e.g. a "
                                         "\\ud800 escape)") from None


def parse_json(text: str, what: str, max_chars: int, max_depth: int = MAX_JSON_DEPTH,
               max_string: int = MAX_STRING_CHARS) -> Any:
    """``text`` parsed as strict JSON within limits; :class:`UntrustedJSONError` names ``what``.

    Refused, and never echoed: a text that is not a ``str``, more than ``max_chars`` characters,
    nesting deeper than ``max_depth`` (checked by a linear scan before parsing, so the parser never
    recurses deep whatever the recursion limit), NaN/Infinity, numbers over ``MAX_NUMBER_CHARS``
    characters or beyond float range, duplicate keys, strings or keys over ``max_string``
    characters, and invalid Unicode (lone surrogates).
    """
    if not isinstance(text, str):
        raise UntrustedJSONError(f"{what} must be text, got {type(text).__name__}")
    if len(text) > max_chars:
        raise UntrustedJSONError(f"{what} is over the {max_chars} character limit")
    if json_depth(text) > max_depth:
        raise UntrustedJSONError(f"{what} nests deeper than {max_depth} levels")
    try:
        value = json.loads(text, object_pairs_hook=_no_duplicates, parse_constant=_reject_constant,
                           parse_int=_parse_number(int), parse_float=_parse_number(float))
    except json.JSONDecodeError as exc:
        raise UntrustedJSONError(f"{what} is not valid JSON ({exc.msg} at character {exc.pos})") from None
    except _JSONLimit as exc:
        raise UntrustedJSONError(f"{what} is not valid JSON: {exc}") from None
    except (ValueError, RecursionError, MemoryError) as exc:
        raise UntrustedJSONError(f"{what} is not valid JSON ({type(exc).__name__})") from None
    _check_strings(value, what, max_string)
    return value
