"""The executor the MEDC nodes spin on.

rclpy's EventsExecutor (rclpy.experimental, Jazzy) dispatches callbacks from a C++ event queue
instead of rebuilding a wait set in Python on every spin, which cuts the per-message cost several
times; an agent node handles 2N+2 messages per team step, so this is most of its decision time.
``MEDC_EXECUTOR=single`` selects the classic SingleThreadedExecutor.
"""

from __future__ import annotations

import os
import signal
import threading

#: Set by SIGINT/SIGTERM in a node process run by :func:`run_node`: the spin loops end at the
#: next spin_once boundary, and only then are the executor, the node and the context shut down.
_STOP = threading.Event()


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


def request_stop(*_: object) -> None:
    """Ask the spin loops of this process to end (the SIGINT/SIGTERM handler of :func:`run_node`)."""
    _STOP.set()


def running() -> bool:
    """True while rclpy is up and no stop was requested: the condition of every spin loop."""
    import rclpy

    return rclpy.ok() and not _STOP.is_set()


def install_stop_handlers() -> None:
    """Make SIGINT and SIGTERM request a stop instead of shutting the context down.

    rclpy's own handler shuts the context down from the signal, asynchronously: a callback the
    executor is already running (or dispatches from its queue afterwards) then publishes on a
    dead context and the EventsExecutor logs ``[FATAL] Exception in 'subscriptions' callback:
    ... publisher's context is invalid`` with a traceback. Here the signal only sets a flag; the
    spin loop ends between two callbacks and :func:`run_node` shuts down in order.
    """
    _STOP.clear()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, request_stop)


def spin_until_shutdown(node, executor) -> None:
    """Spin until a stop is requested or rclpy shuts down; spin_once in a loop (not spin()) so that
    Ctrl-C and the launcher's SIGINT are seen within 0.1 s."""
    while running():
        if not spin_once_alive(executor, 0.1):
            return


def spin_once_alive(executor, timeout_sec: float) -> bool:
    """``executor.spin_once(timeout_sec)``; False when rclpy was shut down during it.

    A SIGINT handled by rclpy's own signal handler (or the launcher's SIGINT to a node) can shut the
    context down while the executor is inside spin_once: taking a message or converting an event on
    a handle that has just become invalid then raises ``RuntimeError`` (from pybind11, e.g. "Unable
    to convert call argument '0' to Python object"). That is a shutdown, not an error; a
    RuntimeError while rclpy is still up is a real one and is raised.
    """
    import rclpy

    try:
        executor.spin_once(timeout_sec=timeout_sec)
    except RuntimeError:
        if rclpy.ok():
            raise
        return False
    return True


def run_node(program: str, argv: list[str] | None, make_node, spin=spin_until_shutdown,
             errors: tuple[type[Exception], ...] = (ValueError,), executor_factory=make_executor) -> int:
    """The life of a console-script node: init rclpy, build the node, spin it, clean up.

    SIGINT and SIGTERM end the spin loop (:func:`install_stop_handlers`); then the executor, the
    node and the context are shut down in that order, so no callback runs on a dead context.

    ``make_node()`` builds the node after rclpy is initialised; ``spin(node, executor)`` runs
    it. Ctrl-C and an external shutdown end it with status 0; an exception of ``errors`` (a
    bad parameter, a registry that cannot be reached) is printed as ``program: message``
    with status 2. Call ``require_interfaces()`` before this.
    """
    import sys

    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    rclpy.init(args=sys.argv if argv is None else argv, signal_handler_options=SignalHandlerOptions.NO)
    install_stop_handlers()
    node = None
    executor = None
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
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        if executor is not None:
            executor.shutdown()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0
