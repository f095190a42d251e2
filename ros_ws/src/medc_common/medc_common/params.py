"""Declaring ROS parameters with descriptions, in one line each."""

from __future__ import annotations

import math
from typing import Any

from rcl_interfaces.msg import ParameterDescriptor


def declare(node, name: str, default: Any, description: str, read_only: bool = False) -> Any:
    """Declare parameter ``name`` on ``node`` with a description; returns its value."""
    node.declare_parameter(name, default, ParameterDescriptor(description=description, read_only=read_only))
    return node.get_parameter(name).value


def seconds(name: str, value: Any, zero_ok: bool = False) -> float:
    """``value`` of parameter ``name`` as a finite number of seconds, > 0 (>= 0 with ``zero_ok``).

    Raises:
        ValueError: naming the parameter, what it takes and the value given.
    """
    return number(name, value, zero_ok=zero_ok, what="seconds")


def number(name: str, value: Any, zero_ok: bool = True, what: str = "") -> float:
    """``value`` of parameter ``name`` as a finite number >= 0 (> 0 without ``zero_ok``).

    Raises:
        ValueError: naming the parameter, what it takes and the value given.
    """
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not zero_ok):
        bound = ">= 0" if zero_ok else "> 0"
        unit = f" of {what}" if what else ""
        raise ValueError(f"{name} must be a finite number{unit} {bound}, got {value!r}")
    return v


def count(name: str, value: Any, least: int = 0) -> int:
    """``value`` of parameter ``name`` as an integer >= ``least``.

    Raises:
        ValueError: naming the parameter, what it takes and the value given.
    """
    if int(value) < least:
        raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    return int(value)
