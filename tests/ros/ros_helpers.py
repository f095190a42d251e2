"""Helpers shared by the ROS graph tests (imported by name; tests/ros is on sys.path)."""

from __future__ import annotations

from pathlib import Path


def training_env(*, seed: int, agents: int, walls: int, grid: int, max_steps: int, observation: str = "maps",
                 sensing: str | None = None, posterior: bool = False):
    """The target-localization core (B = 1) that the simulator node runs, producing the observation a
    policy takes: noise-free, or under ``sensing`` (a preset name) with that preset's noise.
    ``posterior``: its team memory keeps the source posterior (what a classical controller reads)."""
    from medc_training.envs import make_batched

    extra = {"noise": False} if sensing is None else {"sensing": sensing, "noise": None}
    return make_batched("target_localization", num_envs=1, device="cpu", seed=seed, agents=agents,
                        walls=walls, grid=grid, max_steps=max_steps, reward_shaping=False,
                        observation=observation, posterior=posterior, **extra)


def controller_reference_episodes(name: str, episodes: int, *, seed: int, agents: int, walls: int, grid: int,
                                  max_steps: int, sensing: str | None = None):
    """Play ``episodes`` with the training environment and classical controller ``name`` (greedy),
    through the evaluator's play loop: returns (lengths, successes, trace) as
    :func:`reference_episodes` does."""
    from medc_training.controllers import controller_policy

    env = training_env(seed=seed, agents=agents, walls=walls, grid=grid, max_steps=max_steps, sensing=sensing,
                       posterior=True)
    return _play_traced(env, controller_policy(name, env), episodes, seed)


def _play_traced(env, policy, episodes: int, seed: int):
    from medc_lab.window import play

    trace: list[tuple[int, int, list[int]]] = []
    clock = {"episode": 0, "step": 0}

    def record(actions, out) -> None:
        trace.append((clock["episode"], clock["step"], [int(a) for a in actions[0]]))
        clock["step"] += 1
        if bool(out.done[0]):
            clock["episode"], clock["step"] = clock["episode"] + 1, 0

    played = play(env, policy, episodes=episodes, greedy=True, seed=seed, on_step=record)
    return list(played.lengths), list(played.successes), trace


def feed_step(observers, core, stamp, map_stamp, ids, geometry) -> None:
    """Hand every observer the poses, readings and status of ``core``'s current step, as the
    simulator node's messages (agent ids ``ids``, map geometry ``geometry``)."""
    from medc_sim import messages

    for o in observers:
        for j, (cell, value) in enumerate(zip(core.positions(), core.readings())):
            o.add_pose(ids[j], messages.pose_msg(cell, stamp, geometry))
            o.add_reading(ids[j], messages.reading_msg(ids[j], value, 0.0, stamp))
        o.add_status(messages.status_msg(ids, core.episode, core.step, stamp, map_stamp))


def observe_as_reference(observers, ref_obs, ref_mask, gen) -> list[int]:
    """Check that every observer is ready and observes, bit for bit, its row of the reference
    environment's observation ``ref_obs`` [1,N,...] and move mask ``ref_mask`` [1,N,A]; return one
    random valid move per agent (drawn from ``gen``)."""
    import torch

    actions = []
    for i, o in enumerate(observers):
        assert o.ready()
        obs, mask, _ = o.observe()
        assert torch.equal(obs, ref_obs[0, i]) and torch.equal(mask, ref_mask[0, i])
        actions.append(int(torch.rand(8, generator=gen).masked_fill(~mask, -1).argmax()))
    return actions


def reference_episodes(
    bundle: Path, episodes: int, *, seed: int, agents: int, walls: int, grid: int, max_steps: int,
    sensing: str | None = None,
):
    """Play ``episodes`` with the training environment and ``bundle`` greedy, through the play
    loop that training's evaluations use (under the ``sensing`` preset, when given).

    Returns (lengths, successes, trace) with trace = [(episode, step, actions)] like SimCore.trace.
    """
    from medc_training.bundle import load_bundle
    from medc_training.evaluate import net_policy

    policy = load_bundle(bundle)
    env = training_env(seed=seed, agents=agents, walls=walls, grid=grid, max_steps=max_steps,
                       observation=policy.observation, sensing=sensing)
    return _play_traced(env, net_policy(policy.net, policy.device), episodes, seed)


def start_node_process(cmd: list[str], log: Path):
    """Start a node process (``cmd``) writing stdout and stderr to ``log``, unbuffered, in a session
    of its own (so :func:`stop_node_processes` can kill whatever it started)."""
    import os
    import subprocess

    return subprocess.Popen(cmd, stdout=log.open("w"), stderr=subprocess.STDOUT,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"}, start_new_session=True)


def stop_node_processes(procs, wait_s: float = 20.0) -> None:
    """SIGINT to every process of ``procs`` still running; whichever has not ended ``wait_s`` later
    is killed, with its process group when it leads one (:func:`start_node_process` starts each in
    a session of its own)."""
    import os
    import signal
    import subprocess

    for p in procs:
        if p.poll() is None:
            p.send_signal(signal.SIGINT)
    for p in procs:
        try:
            p.wait(wait_s)
        except subprocess.TimeoutExpired:
            if os.getpgid(p.pid) == p.pid:
                os.killpg(p.pid, signal.SIGKILL)
            else:
                p.kill()
            p.wait()


def spin_until(executor, condition, timeout_s: float) -> bool:
    """Spin ``executor`` until ``condition()`` holds; False on timeout."""
    import time

    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            return False
        executor.spin_once(timeout_sec=0.05)
    return True


def replay_masks(trace, *, seed: int, agents: int, walls: int, grid: int, max_steps: int):
    """The move masks [N,A] the agents had at each step of ``trace``, by replaying it in the env."""
    import torch

    env = training_env(seed=seed, agents=agents, walls=walls, grid=grid, max_steps=max_steps)
    _, mask = env.reset()
    masks = []
    for _, _, actions in trace:
        masks.append(mask[0].clone())
        mask = env.step(torch.tensor([actions])).mask
    return masks


class DiagnosticsListener:
    """A test node that records every status published on /diagnostics with the (monotonic) time it
    came, spun on its own executor; subclasses subscribe to more on ``self.node``."""

    def __init__(self, name: str = "diagnostics_listener") -> None:
        import time

        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy

        self.node = rclpy.create_node(name)
        #: (time received, diagnostic_msgs/DiagnosticStatus), in arrival order.
        self.diagnostics: list[tuple[float, object]] = []
        #: (when its node published it: the array's header stamp, ROS time in s, status), in arrival order.
        self.published: list[tuple[float, object]] = []

        def on_diagnostics(msg) -> None:
            sent = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            self.diagnostics.extend((time.monotonic(), s) for s in msg.status)
            self.published.extend((sent, s) for s in msg.status)

        self.node.create_subscription(DiagnosticArray, "/diagnostics", on_diagnostics,
                                      QoSProfile(depth=200, reliability=ReliabilityPolicy.RELIABLE))
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)

    def spin(self, seconds: float, until=None, procs=()) -> bool:
        """Spin up to ``seconds``, asserting that every process of ``procs`` stays alive; True as
        soon as ``until()`` holds (without ``until``: after the time)."""
        import time

        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.05)
            assert all(p.poll() is None for p in procs), "a node died"
            if until is not None and until():
                return True
        return until is None

    def statuses(self) -> list:
        """Every diagnostic status received."""
        return [s for _, s in self.diagnostics]

    def heartbeats(self, name: str, since: float) -> list[float]:
        """When node ``name`` published its heartbeats (the status named after the node), as their
        own stamps (ROS time, s: ``time.time()`` unless a node runs on simulated time), from
        ``since`` on: the node's pace, whatever this listener's."""
        return [t for t, s in self.published if t >= since and s.name == name]

    def warnings(self, since: float, text: str, name_part: str = "") -> list:
        """The WARN statuses received since ``since`` whose message holds ``text`` and whose name
        holds ``name_part``."""
        from diagnostic_msgs.msg import DiagnosticStatus

        return [s for t, s in self.diagnostics if t >= since and s.level == DiagnosticStatus.WARN
                and text in s.message and name_part in s.name]

    def close(self) -> None:
        self.executor.shutdown()
        self.node.destroy_node()


def run_contract_driver(listener: DiagnosticsListener, args: list[str], *, timeout_s: float, procs=(),
                        logs=(), on_poll=None) -> str:
    """Run tests/ros/contract_driver.py with ``args`` to its end while ``listener`` spins, asserting
    that it ends within ``timeout_s`` with success and that every process of ``procs`` stays alive
    (the tails of ``logs`` say why one died); ``on_poll()`` is called between spins. Returns what
    the driver printed."""
    import os
    import subprocess
    import sys
    import time

    driver = Path(__file__).resolve().parent / "contract_driver.py"
    proc = subprocess.Popen([sys.executable, str(driver), *args], env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    start = time.monotonic()
    try:
        while proc.poll() is None:
            listener.executor.spin_once(timeout_sec=0.05)
            assert time.monotonic() - start < timeout_s, "the team stopped stepping"
            assert all(p.poll() is None for p in procs), [Path(p).read_text()[-2000:] for p in logs]
            if on_poll is not None:
                on_poll()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    text = proc.stdout.read()
    assert proc.returncode == 0, text[-3000:]
    return text


def load_launch_file():
    """ros_ws/src/medc_bringup/launch/medc.launch.py as a module, loaded as ``ros2 launch`` loads
    it before calling generate_launch_description (launch/launch_ros are not needed to load it)."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "ros_ws" / "src" / "medc_bringup" / "launch"
    spec = importlib.util.spec_from_file_location("medc_launch_file", path / "medc.launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def descendants(pid: int) -> list[int]:
    """Every process below ``pid`` (children, their children, ...), read from /proc."""
    import os

    parents: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as f:
                # The name (field 2) may hold spaces; the parent pid is the 2nd field after it.
                ppid = int(f.read().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        parents.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for child in parents.get(todo.pop(), []):
            out.append(child)
            todo.append(child)
    return out


def stop_launcher(proc, grace_s: float = 20.0) -> None:
    """Stop a ``medc-launch`` process ``proc`` started with ``start_new_session=True`` and every node
    it started, whatever state it is in: SIGINT first (the launcher stops its nodes itself), then
    SIGKILL to the process group of the launcher and of each process it started (every node runs
    in a session of its own), so that a hung graph never outlives its test."""
    import contextlib
    import os
    import signal
    import subprocess

    tree = descendants(proc.pid)
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(grace_s)
    for pid in [proc.pid, *tree]:
        # Gone already, or not a group of its own (then its group's leader is in the list).
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.killpg(pid, signal.SIGKILL)
    proc.wait()


def run_launcher(args: list[str], cwd: Path, timeout_s: float, stderr_file: Path, env=None):
    """Run ``python -m medc_bringup.launcher ARGS`` in ``cwd``; its stderr (and every node's) goes to
    ``stderr_file`` (a file, not a pipe: the nodes' logs can never block). Returns
    ``(returncode, stdout)``; on timeout stops it and its nodes (:func:`stop_launcher`) and
    raises ``subprocess.TimeoutExpired``."""
    import subprocess
    import sys

    with stderr_file.open("w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "medc_bringup.launcher", *args],
                                stdout=subprocess.PIPE, stderr=log, text=True, cwd=cwd, env=env,
                                start_new_session=True)
        try:
            out, _ = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            stop_launcher(proc)
            proc.communicate()
            raise
        finally:
            if proc.poll() is None:
                stop_launcher(proc)
    return proc.returncode, out
