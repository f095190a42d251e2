"""The executor the MEDC nodes spin on.

rclpy's EventsExecutor (rclpy.experimental, Jazzy) dispatches callbacks from a C++ event queue
instead of rebuilding a wait set in Python on every spin, which cuts the per-message cost several
times; an agent node handles 2N+2 messages per team step, so this is most of its decision time.
``MEDC_EXECUTOR=single`` selects the classic SingleThreadedExecutor.
"""

from __future__ import annotations

import os
import re
import signal
import sys
import threading
from collections.abc import Iterator

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


def stop_requested() -> bool:
    """True once SIGINT or SIGTERM asked this process to stop (:func:`install_stop_handlers`)."""
    return _STOP.is_set()


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


class BadRosArguments(ValueError):
    """The ``--ros-args`` of a node's command line cannot be used; the message names the argument."""


#: Where rcl says where in its sources it failed (", at /project/src/rcl/arguments.c:380"): not
#: for the user.
_RCL_SOURCE = re.compile(r",? at \S+\.c:\d+")
#: A line of rcl's own log (what it warns about before failing).
_RCL_LOG = re.compile(r"^\[(?:WARN|ERROR)\] \[[\d.]+\] \[rcl\]: (.*)$")


def ros_argument_values(args: list[str], flags: tuple[str, ...]) -> Iterator[tuple[str, str]]:
    """``(flag, value)`` of every ``FLAG VALUE`` pair among ``flags`` inside the ``--ros-args``
    sections of ``args`` (each up to its ``--``), in order."""
    inside = False
    for i, arg in enumerate(args):
        if arg == "--ros-args":
            inside = True
        elif arg == "--":
            inside = False
        elif inside and arg in flags and i + 1 < len(args):
            yield arg, args[i + 1]


def _remapped_namespaces(args: list[str]) -> list[tuple[str, str]]:
    """``(argument, namespace)`` of every ``-r [node:]__ns:=NS`` in the ``--ros-args`` of ``args``."""
    out = []
    for flag, rule in ros_argument_values(args, ("-r", "--remap")):
        name, sep, value = rule.partition(":=")
        if sep and name.rsplit(":", 1)[-1] == "__ns":
            out.append((f"{flag} {rule}", value))
    return out


def init_ros(args: list[str], signal_handler_options=None) -> None:
    """``rclpy.init(args=args)``; arguments it cannot use are refused with one line.

    A namespace remap (``-r __ns:=NS``) is checked first as the nodes check a namespace
    (:func:`medc_common.contract.check_namespace`, which gives the reason); any other argument rcl
    refuses is named from rcl's own error, without its source locations. rcl's log lines of a
    failed start (``[rcl]: Failed to parse global arguments``) are kept off stderr; those of a
    start that works are passed on.

    Raises:
        BadRosArguments: the argument and why it cannot be used.
    """
    import rclpy

    from medc_common.contract import check_namespace

    for arg, namespace in _remapped_namespaces(list(args)):
        if not namespace.startswith("/"):
            raise BadRosArguments(f"{arg}: a node namespace must be fully qualified (start with '/'); "
                                  "see --help")
        try:
            check_namespace(namespace)
        except ValueError as exc:
            raise BadRosArguments(f"{arg}: {exc}; see --help") from None
    log = _capture_stderr()
    try:
        with log:
            if signal_handler_options is None:
                rclpy.init(args=args)
            else:
                rclpy.init(args=args, signal_handler_options=signal_handler_options)
    except RuntimeError as exc:  # rclpy's RCLError, or UnknownROSArgsError
        if type(exc).__name__ == "UnknownROSArgsError":  # its message is the list of arguments
            raise BadRosArguments(f"unknown ROS arguments {exc} (a value with a space must be quoted); "
                                  "see --help") from None
        said = [m.group(1) for m in map(_RCL_LOG.match, log.text.splitlines()) if m]
        why = [w for w in said if "Failed to parse global arguments" not in w]
        text = _RCL_SOURCE.sub("", str(exc)).removeprefix("failed to initialize rcl: ").strip()
        text = re.sub(r"\. Error: (error not set|Expected lexeme[^.]*)$", "", text)
        raise BadRosArguments(f"cannot start with these ROS arguments: {text}"
                              + (f" ({'; '.join(why)})" if why else "") + "; see --help") from None
    if log.text:
        sys.stderr.write(log.text)
        sys.stderr.flush()


class _capture_stderr:
    """Everything written to file descriptor 2 (by C code too) inside the ``with`` block, as
    ``.text`` afterwards; nothing of it reaches stderr."""

    def __init__(self) -> None:
        self.text = ""

    def __enter__(self):
        import tempfile

        sys.stderr.flush()
        self._file = tempfile.TemporaryFile()
        self._saved = os.dup(2)
        os.dup2(self._file.fileno(), 2)
        return self

    def __exit__(self, *exc) -> None:
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._file.seek(0)
        self.text = self._file.read().decode("utf-8", "replace")
        self._file.close()


_WRONG_TYPE = re.compile(r"Trying to set parameter '(?P<name>.*)' to '(?P<value>.*)' of type "
                         r"'(?P<given>\w+)', expecting type '(?:Type\.)?(?P<wanted>\w+)'")


def parameter_problem(exc: Exception) -> str:
    """One line for rclpy's refusal of a parameter (a value of the wrong type, one left unset)."""
    text = " ".join(str(exc).split())
    wrong = _WRONG_TYPE.match(text)
    if wrong is None:
        return f"bad parameter: {text}"
    kind = {"BOOL": "true or false", "INTEGER": "an integer", "DOUBLE": "a number", "STRING": "text"}
    name, wanted, given = wrong["name"], wrong["wanted"], wrong["given"]
    value = "".join(c if c.isprintable() else "?" for c in wrong["value"][:80])
    return (f"-p {name}:={value}: that is {kind.get(given, given.lower())}; "
            f"{name} takes {kind.get(wanted, wanted.lower())} (see --help)")


def run_node(program: str, argv: list[str] | None, make_node, spin=spin_until_shutdown,
             errors: tuple[type[Exception], ...] = (ValueError,), executor_factory=make_executor) -> int:
    """The life of a console-script node: init rclpy, build the node, spin it, clean up.

    SIGINT and SIGTERM end the spin loop (:func:`install_stop_handlers`); then the executor, the
    node and the context are shut down in that order, so no callback runs on a dead context.

    Arguments rcl cannot parse (a remap, a parameter override, a log level, a params file) end it
    before any node exists with one line naming the argument and status 2 (:func:`init_ros`).
    ``make_node()`` builds the node after rclpy is initialised; ``spin(node, executor)`` runs
    it. Ctrl-C and an external shutdown end it with status 0; an exception of ``errors`` (a
    bad parameter, a registry that cannot be reached) is printed as ``program: message``
    with status 2, as is a parameter rclpy refuses (a value of the wrong type:
    :func:`parameter_problem`). Call ``require_interfaces()`` before this.
    """

    import rclpy
    from rclpy.exceptions import ParameterException
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    try:
        init_ros(sys.argv if argv is None else argv, SignalHandlerOptions.NO)
    except BadRosArguments as exc:
        print(f"{program}: {exc}", file=sys.stderr)
        return 2
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
    except ParameterException as exc:  # a value of the wrong type, given with -p or a params file
        print(f"{program}: {parameter_problem(exc)}", file=sys.stderr)
        return 2
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
