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


def spin_until_shutdown(node, executor) -> None:
    """Spin until rclpy shuts down; spin_once in a loop (not spin()) so that Ctrl-C and the
    launcher's SIGINT are seen within 0.1 s."""
    import rclpy

    while rclpy.ok():
        try:
            executor.spin_once(timeout_sec=0.1)
        except RuntimeError:
            # The launcher's SIGINT can shut the context down while the EventsExecutor is inside
            # spin_once, which then fails converting its now-invalid handles: that is a shutdown,
            # not an error. A RuntimeError while rclpy is still up is a real one.
            if rclpy.ok():
                raise
            return


def run_node(program: str, argv: list[str] | None, make_node, spin=spin_until_shutdown,
             errors: tuple[type[Exception], ...] = (ValueError,), executor_factory=make_executor) -> int:
    """The life of a console-script node: init rclpy, build the node, spin it, clean up.

    ``make_node()`` builds the node after rclpy is initialised; ``spin(node, executor)`` runs
    it. Ctrl-C and an external shutdown end it with status 0; an exception of ``errors`` (a
    bad parameter, a registry that cannot be reached) is printed as ``program: message``
    with status 2. Call ``require_interfaces()`` before this.
    """
    import signal
    import sys

    import rclpy
    from rclpy.executors import ExternalShutdownException

    rclpy.init(args=sys.argv if argv is None else argv)
    node = None
    try:
        node = make_node()
        executor = executor_factory()
        executor.add_node(node)
        spin(node, executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except errors as exc:
        print(f"{program}: {exc}", file=sys.stderr)
        return 2
    finally:
        # A second Ctrl-C (or the launcher's SIGINT) must not cut the clean-up short.
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
