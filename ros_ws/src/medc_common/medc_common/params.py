"""Declaring ROS parameters with descriptions, in one line each."""

from __future__ import annotations

from typing import Any

from rcl_interfaces.msg import ParameterDescriptor


def declare(node, name: str, default: Any, description: str, read_only: bool = False) -> Any:
    """Declare parameter ``name`` on ``node`` with a description; returns its value."""
    node.declare_parameter(name, default, ParameterDescriptor(description=description, read_only=read_only))
    return node.get_parameter(name).value
