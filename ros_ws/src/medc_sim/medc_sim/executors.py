"""The executor the MEDC nodes spin on.

rclpy's EventsExecutor (rclpy.experimental, Jazzy) dispatches callbacks from a C++ event queue
instead of rebuilding a wait set in Python on every spin, which cuts the per-message cost several
times; an agent node handles 2N+2 messages per team step, so this is most of its decision time.
``MEDC_EXECUTOR=single`` selects the classic SingleThreadedExecutor.
"""

from __future__ import annotations

import os


def make_executor():
    """A new executor: EventsExecutor unless ``MEDC_EXECUTOR=single`` or it is unavailable."""
    from rclpy.executors import SingleThreadedExecutor

    if os.environ.get("MEDC_EXECUTOR", "events") == "single":
        return SingleThreadedExecutor()
    try:
        from rclpy.experimental import EventsExecutor
    except ImportError:
        return SingleThreadedExecutor()
    return EventsExecutor()
