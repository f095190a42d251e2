"""medc-launch: start the whole MEDC graph (simulator, one agent node per agent, optionally the
registry bridge) from one YAML config, and stop it cleanly on Ctrl-C.

The pip-installed ROS has no ``ros2 launch``; this is the project's launcher. By default every
node runs as its own process through its console script (``medc-sim``, ``medc-agent``,
``medc-bridge``); ``--in-process`` runs them all in this process on one executor.

    medc-launch                               # the default team (infotaxis, realistic 20x20), until Ctrl-C
    medc-launch --episodes 20                 # 20 episodes, one line each, then one JSON line
    medc-launch --policy models/team          # the shipped trained team (paper-simple, 13x13)
    medc-launch --config my.yaml --seed 3 --policy path/to/bundle.safetensors
    medc-launch --sensing realistic --policy path/to/realistic_bundle.safetensors
    medc-launch --policy greedy --episodes 20  # a team of classical controllers (also gradient, infotaxis)
    medc-launch --episodes 5 --record run.mcap # and record every topic (rosbag2's MCAP; medc-record)
    medc-launch --foxglove                    # and watch it live in Foxglove: ws://127.0.0.1:8765
    medc-launch --namespace /team2            # the whole team under /team2 (each node: -r __ns:=/team2)
    medc-launch --listeners 1                 # the first step waits for one more reader of the status
                                              # and results topics (a tool started on its own)
    medc-launch --authenticate                # sign and verify the team's messages under a new mission key
    medc-launch --authenticate --key-file k   # ... under the key in k (written 0600 when k does not exist)

``--authenticate`` issues a random mission key to a 0600 file (``--key-file``, else a private folder
removed at the end) and gives its path to every node (``MEDC_AUTH_KEY_FILE``, read by each node's
``auth_key_file`` parameter): statuses, readings, moves and declarations are signed and only
verified ones are used (docs/security.md). Without it the graph runs in the open mode.

A relative ``--policy`` is taken from the current directory; a relative ``policy`` in the config
file (e.g. ``models/team``) from the repository root. Without ``--policy`` the default config runs
infotaxis on the realistic preset (20x20, 2 walls, 100 steps), the team measured best there.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml
from medc_common.contract import agent_node_name
from medc_common.ros_env import interfaces_env, repo_root, require_interfaces
from medc_common.share import config_file

from medc_bringup.live_view import DEFAULT_MAX_CLIENTS

#: The installed share/medc_bringup/config/launch.yaml (ament index), else the source tree's.
DEFAULT_CONFIG = config_file("medc_bringup", "launch.yaml")
#: Scenario used when neither the config nor the policy's manifest says otherwise.
SCENARIO_DEFAULTS = {"agents": 3, "walls": 2, "grid": 30, "max_steps": 100}
#: A classical controller's team has no manifest: the keys the config leaves unset take the realistic
#: preset's scenario (RAD-A2C's 20x20 m area), where the controllers are the measured best teams
#: (docs/environments.md, "Realistic search results"): config/launch.yaml's default team.
CONTROLLER_DEFAULTS = {"agents": 3, "walls": 2, "grid": 20, "max_steps": 100}
CONTROLLER_SENSING = "realistic"
#: Seconds the graph stays up after its last episode when a recorder in another process listens:
#: it gets the last messages (the final moves, the last result) only while their reliable writers
#: live. medc-sim lingers as long.
RECORDER_LINGER_S = 1.0


@dataclass
class LaunchConfig:
    """What the launcher starts (keys of the YAML config; see config/launch.yaml)."""

    namespace: str = "/medc"
    # None = taken from the policy bundle's manifest (the scenario it was trained on).
    agents: int | None = None
    walls: int | None = None
    grid: int | None = None
    max_steps: int | None = None
    seed: int = 0
    noise: bool = False
    # The sensing preset of the simulator and every agent; None = the policy bundle's manifest's
    # (environment.sensing; a manifest without it: paper-simple).
    sensing: str | None = None
    mode: str = "stepped"
    #: What ends an episode besides max_steps (medc_sim.episode_end): source, declaration, either.
    end_on: str = "source"
    rate_hz: float = 0.0
    resolution: float = 1.0
    policy: str = "models/team"
    policies: dict[str, str] = field(default_factory=dict)
    #: Run a bundle trained in another world or with domain randomisation (its manifest's
    #: environment.world, randomisation options, walls_min, snr_max) in this graph's world anyway.
    allow_other_world: bool = False
    #: The world the simulator and the agents play (grid, radbench); None = the policy bundle's
    #: manifest's (environment.world; none = grid; a classical controller: grid).
    world: str | None = None
    #: The agents' background prior in the radbench world ("LOW,HIGH,LEVELS"; empty: the bundle's).
    prior_background: str = ""
    #: The agents' classical endgame (medc_agents.bench_team): the posterior mass that starts it.
    endgame_tau: float = 1.0
    registry: dict[str, Any] = field(default_factory=lambda: {"enabled": False, "params": {}})


def load_config(path: str | os.PathLike[str] | None = None, **overrides: Any) -> LaunchConfig:
    """Read a launch config (default: config/launch.yaml) and apply ``overrides`` (None = keep).

    Raises:
        ValueError: unreadable YAML, unknown keys, or a value of the wrong type.
    """
    path = Path(path) if path is not None else DEFAULT_CONFIG
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f"cannot read launch config {path}: {exc}") from exc
    if not isinstance(data, dict):
        raise ValueError(f"launch config {path} must be a mapping of keys to values")
    known = {f.name: f for f in fields(LaunchConfig)}
    unknown = sorted(set(data) - set(known))
    if unknown:
        raise ValueError(f"unknown key(s) {unknown} in {path}; allowed: {sorted(known)}")
    data.update({k: v for k, v in overrides.items() if v is not None})
    cfg = LaunchConfig(**data)
    for name, kind in (
        ("agents", int),
        ("walls", int),
        ("grid", int),
        ("max_steps", int),
        ("seed", int),
        ("rate_hz", (int, float)),
        ("resolution", (int, float)),
        ("noise", bool),
        ("allow_other_world", bool),
        ("prior_background", str),
        ("endgame_tau", (int, float)),
        ("policy", str),
        ("policies", dict),
        ("registry", dict),
    ):
        value = getattr(cfg, name)
        if value is None and name in SCENARIO_DEFAULTS:
            continue
        if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
            raise ValueError(
                f"{name} in {path} must be {getattr(kind, '__name__', 'a number')}, got {value!r}"
            )
    if not isinstance(cfg.namespace, str):
        raise ValueError(f"namespace in {path} must be str, got {cfg.namespace!r}")
    from medc_common.contract import check_namespace

    cfg.namespace = check_namespace(cfg.namespace)  # ValueError naming what is wrong with it
    if cfg.mode not in ("stepped", "realtime"):
        raise ValueError(f"mode must be 'stepped' or 'realtime', got {cfg.mode!r}")
    if cfg.end_on not in ("source", "declaration", "either"):
        raise ValueError(f"end_on in {path} must be 'source', 'declaration' or 'either', got {cfg.end_on!r}")
    if cfg.sensing is not None:
        from medc_training.envs.tl_sensing import SENSING_PRESETS

        if not isinstance(cfg.sensing, str) or cfg.sensing not in SENSING_PRESETS:
            raise ValueError(f"sensing in {path} must be one of {sorted(SENSING_PRESETS)} or null "
                             f"(the policy bundle's), got {cfg.sensing!r}")
    _check_world_keys(cfg, path)
    cfg.rate_hz, cfg.resolution = float(cfg.rate_hz), float(cfg.resolution)
    return cfg


def _check_world_keys(cfg: LaunchConfig, path: Path) -> None:
    """Check ``world``, ``prior_background`` and ``endgame_tau`` of a launch config read from
    ``path`` (ValueError saying what each takes)."""
    from medc_agents.bench_team import WORLDS, check_endgame_tau
    from medc_training.radbench.physics import background_prior

    if cfg.world is not None and cfg.world not in WORLDS:
        raise ValueError(f"world in {path} must be one of {', '.join(WORLDS)} or null (the policy bundle's), "
                         f"got {cfg.world!r}")
    if cfg.prior_background.strip():
        try:
            background_prior(cfg.prior_background)
        except ValueError as exc:
            raise ValueError(f"prior_background in {path}: {exc} (empty: the policy bundle's)") from None
    try:
        cfg.endgame_tau = check_endgame_tau(cfg.endgame_tau)
    except ValueError as exc:
        raise ValueError(f"{exc} (launch config {path})") from None


def _absolute(path: str, root: Path) -> Path:
    q = Path(path).expanduser()
    return q if q.is_absolute() else root / q


def _controllers() -> tuple[str, ...]:
    """Every classical controller's name (medc_training.controllers.CONTROLLERS)."""
    from medc_training.controllers import CONTROLLERS

    return CONTROLLERS


def _controller(policy: object) -> str | None:
    """The classical controller ``policy`` names (:func:`_controllers`), or None."""
    return policy.strip() if isinstance(policy, str) and policy.strip() in _controllers() else None


def _complete_scenario(cfg: LaunchConfig, base: Path | None) -> None:
    """Fill the scenario keys left unset (and ``sensing``) from the manifest of the bundle at
    ``base`` (file or folder); None (a controller): the realistic preset's scenario
    (CONTROLLER_DEFAULTS, CONTROLLER_SENSING)."""
    from medc_training.bundle import BundleError, manifest_sensing, read_manifest

    missing = [k for k in SCENARIO_DEFAULTS if getattr(cfg, k) is None]
    if not missing and cfg.sensing is not None and cfg.world is not None:
        return
    if base is None:
        sample = None
    else:
        sample = base if base.is_file() else next(iter(sorted(base.glob("*.safetensors"))), None)
    env: dict[str, Any] = {}
    if sample is not None:
        try:
            manifest = read_manifest(sample)
            env = manifest.get("environment") or {}
            if cfg.sensing is None:
                cfg.sensing = manifest_sensing(manifest)
            if cfg.world is None:
                cfg.world = str(env.get("world", "grid"))
        except BundleError as exc:
            raise ValueError(f"policy {sample} is not a valid bundle: {exc}") from exc
    if cfg.sensing is None:
        from medc_training.envs.tl_sensing import DEFAULT_SENSING

        cfg.sensing = CONTROLLER_SENSING if base is None else DEFAULT_SENSING
    if cfg.world is None:
        cfg.world = "grid"
    defaults = CONTROLLER_DEFAULTS if base is None else SCENARIO_DEFAULTS
    for key in missing:
        value = env.get(key)
        setattr(
            cfg,
            key,
            int(value) if isinstance(value, int) and not isinstance(value, bool) else defaults[key],
        )


def _check_fits(cfg: LaunchConfig, paths: list[str]) -> None:
    """Every bundle must take this scenario's observation (the variant its manifest names, on this
    grid), have been trained under its sensing preset (in the radbench world: the team model under
    the agents' background prior) and, unless ``allow_other_world``, in the graph's world without
    domain randomisation, or its agent would refuse it; the simulator must take the scenario in its
    world."""
    from medc_agents.bench_team import team_model
    from medc_sim.sim_core import SimConfig, check_world_options
    from medc_training.bundle import (
        BundleError,
        check_sensing,
        check_world,
        manifest_observation,
        read_manifest,
    )
    from medc_training.envs.tl_observation import observation_shape

    for path in sorted({p for p in paths if _controller(p) is None}):
        try:
            manifest = read_manifest(path)
            obs = manifest["observation"]
            name = manifest_observation(manifest) or "maps"
            expected = observation_shape(name, cfg.grid)
        except (BundleError, ValueError) as exc:
            raise ValueError(f"policy {path} is not a valid bundle: {exc}") from exc
        shape = (obs.get("channels"), obs.get("height"), obs.get("width"))
        if shape != expected:
            raise ValueError(
                f"policy {path} takes observations of shape {shape}, but a {cfg.grid}x{cfg.grid} grid gives "
                f"{expected} for its observation {name}; set grid: "
                f"{obs.get('height')} or use a bundle trained on this grid"
            )
        try:
            check_world(manifest, cfg.world, cfg.allow_other_world, f"policy {path}")
        except BundleError as exc:  # its message names the world, the options and the way around
            mine = str((manifest.get("environment") or {}).get("world", "grid"))
            where = "" if mine == cfg.world else (f"; to simulate its world set world: {mine[:40]} (or null, "
                                                  "the policy bundle's) in the launch config")
            raise ValueError(f"{exc} (launch config key allow_other_world){where}") from exc
        try:
            check_sensing(manifest, team_model(cfg.world, cfg.sensing, cfg.prior_background, path),
                          f"policy {path}")
        except (BundleError, ValueError) as exc:  # its message names both models and what to change
            raise ValueError(f"{exc} (launch config keys sensing, prior_background)") from exc
    try:  # what the agents and the simulator would refuse at their start
        team_model(cfg.world, cfg.sensing, cfg.prior_background, "")
        check_world_options(SimConfig(agents=cfg.agents, walls=cfg.walls, grid=cfg.grid, sensing=cfg.sensing,
                                      end_on=cfg.end_on, world=cfg.world))
    except ValueError as exc:
        raise ValueError(f"{exc} (launch config)") from None


def resolve_policies(cfg: LaunchConfig, root: Path | None = None) -> list[str]:
    """The bundle path each agent starts with (relative paths in ``cfg`` are taken from ``root``,
    default the repository root; main() makes a relative ``--policy`` absolute from the current
    directory first).

    ``policy`` names one bundle for every agent, or a folder holding ``*agent_<i>*.safetensors``
    files (one per agent) or a single bundle, or a classical controller (``gradient``, ``greedy``,
    ``infotaxis``: medc_training.controllers) every agent runs by name; ``policies`` overrides
    single agents (a bundle path or a controller's name). Scenario keys left unset in ``cfg``
    (agents, walls, grid, max_steps, sensing) are filled in from the bundle's manifest (else
    SCENARIO_DEFAULTS and the default sensing preset; a controller has none: CONTROLLER_DEFAULTS
    and CONTROLLER_SENSING). Every bundle must have
    been trained under ``cfg.sensing`` and, unless ``cfg.allow_other_world``, in the grid world
    without domain randomisation.

    Raises:
        ValueError: a path does not exist, the folder has no usable bundle, or a bundle does not
        fit the scenario's observation shape, sensing preset or world.
    """
    from medc_common import contract
    from medc_common.contract import agent_index

    root = repo_root() if root is None else root
    controller = _controller(cfg.policy)
    base = None if controller else _absolute(cfg.policy, root)
    if base is not None and not base.exists():
        raise ValueError(
            f"policy {cfg.policy!r} ({base}) does not exist (a relative policy in the config is taken "
            f"from {root}); train the team (models/README.md) or pass --policy PATH to a bundle "
            "(a relative --policy is taken from the current directory)"
        )
    _complete_scenario(cfg, base)
    paths: list[str] = []
    if base is None:
        paths = [controller] * cfg.agents
    elif base.is_dir():
        bundles = sorted(base.glob("*.safetensors"))
        if not bundles:
            raise ValueError(
                f"policy folder {base} holds no .safetensors bundle; train the team "
                "(see models/README.md) or pass --policy PATH"
            )
        for i in range(cfg.agents):
            own = [b for b in bundles if contract.agent_id(i) in b.stem or f"agent{i}" in b.stem]
            paths.append(str(own[0] if own else bundles[0]))
    else:
        paths = [str(base)] * cfg.agents
    for agent_id, p in cfg.policies.items():
        i = agent_index(agent_id, cfg.agents)
        if _controller(p):
            paths[i] = _controller(p)
            continue
        if not _absolute(p, root).is_file():
            raise ValueError(f"policy for {agent_id}: {_absolute(p, root)} does not exist")
        paths[i] = str(_absolute(p, root))
    _check_fits(cfg, paths)
    return paths


def sim_parameters(cfg: LaunchConfig, episodes: int = 0, extra_listeners: int = 0,
                   results_readers: int = 0) -> dict[str, Any]:
    """Parameters of the simulator node for ``cfg``; ``extra_listeners``: status subscribers besides
    the agents (a recorder) that must be there before the first step; ``results_readers``: readers
    of the episode results (the launcher's monitor, a recorder) the first step, and the end of a
    finished simulator, wait for (medc_sim.start_gate)."""
    return {
        "wait_for_subscribers": cfg.agents + extra_listeners,
        "wait_for_results_readers": results_readers,
        "agents": cfg.agents,
        "walls": cfg.walls,
        "grid": cfg.grid,
        "max_steps": cfg.max_steps,
        "seed": cfg.seed,
        "noise": cfg.noise,
        # None (resolve_policies not called): the node's default.
        **({} if cfg.sensing is None else {"sensing": cfg.sensing}),
        **({} if cfg.world is None else {"world": cfg.world}),
        "mode": cfg.mode,
        "end_on": cfg.end_on,
        "rate_hz": cfg.rate_hz,
        "resolution": cfg.resolution,
        "episodes": episodes,
    }


def agent_parameters(cfg: LaunchConfig, index: int, policy: str) -> dict[str, Any]:
    """Parameters of agent node ``index`` for ``cfg``."""
    from medc_common.contract import agent_id

    return {
        "agent_id": agent_id(index),
        "agents": cfg.agents,
        "grid": cfg.grid,
        "resolution": cfg.resolution,
        **({} if cfg.sensing is None else {"sensing": cfg.sensing}),
        "noise": cfg.noise,
        # Only a finding that ends the episode lets the team rule out the cells it stood on.
        "source_ends_episode": cfg.end_on != "declaration",
        "allow_other_world": cfg.allow_other_world,
        **({} if cfg.world is None else {"world": cfg.world}),
        "prior_background": cfg.prior_background,
        "endgame_tau": cfg.endgame_tau,
        "policy": policy,
    }


def ros_args(node_name: str, params: dict[str, Any], namespace: str | None = None) -> list[str]:
    """``--ros-args`` command-line arguments that name the node, put it in ``namespace`` (the team's:
    every MEDC name is relative to it; None: the node's default, /medc) and set ``params``."""
    out = ["--ros-args", "-r", f"__node:={node_name}"]
    if namespace is not None:
        out += ["-r", f"__ns:={namespace}"]
    for key, value in params.items():
        if isinstance(value, bool):
            text = "true" if value else "false"
        elif isinstance(value, str):
            text = json.dumps(value)  # quoted: a path or namespace stays a string
        else:
            text = repr(value)
        out += ["-p", f"{key}:={text}"]
    return out


class EpisodeLog:
    """Collects finished episodes and prints one line per episode."""

    def __init__(self, quiet: bool = False) -> None:
        self.lengths: list[int] = []
        self.successes: list[bool] = []
        self.quiet = quiet

    def add(self, episode: int, length: int, success: bool) -> None:
        self.lengths.append(int(length))
        self.successes.append(bool(success))
        if not self.quiet:
            verdict = "target found" if success else "truncated"
            print(f"episode {episode}: {length} steps, {verdict}", flush=True)

    def summary(self, **extra: Any) -> dict[str, Any]:
        n = len(self.lengths)
        return {
            "episodes": n,
            "episode_lengths": self.lengths,
            "successes": self.successes,
            "success_rate": (sum(self.successes) / n) if n else 0.0,
            "mean_length": (sum(self.lengths) / n) if n else 0.0,
            **extra,
        }


def build_graph(
    cfg: LaunchConfig, policies: list[str], episodes: int = 0, record: bool = False, shared_feed: bool = True,
    extra_listeners: int = 0,
):
    """The simulator node and one agent node per agent, for one process (rclpy initialised).

    ``record``: the simulator keeps every applied step in ``sim.core.trace``.
    ``shared_feed``: the agents take the team's messages from one TeamFeed node instead of each
    subscribing to all of them (same messages, same checks, N times fewer deliveries).
    ``extra_listeners``: status subscribers of other processes (a recorder) the first step waits for.
    Returns ``(sim, agents, nodes)``, ``nodes`` = every node to spin (the feed included).
    """
    from medc_agents.node import AgentNode, TeamFeed
    from medc_sim.simulator import SimNode
    from rclpy.parameter import Parameter

    def overrides(params: dict[str, Any]) -> list[Parameter]:
        return [Parameter(k, value=v) for k, v in params.items()]

    # In one process the launcher hears results from the simulator itself; a recorder reads them.
    params = sim_parameters(cfg, episodes, extra_listeners, results_readers=extra_listeners)
    if shared_feed:
        params["wait_for_subscribers"] = 1 + extra_listeners  # the feed listens for every agent
    sim = SimNode(namespace=cfg.namespace, parameter_overrides=overrides(params))
    sim.core.record = record
    feed = TeamFeed(cfg.namespace, cfg.agents) if shared_feed else None
    agents = [
        AgentNode(node_name=agent_node_name(i), feed=feed, namespace=cfg.namespace,
                  parameter_overrides=overrides(agent_parameters(cfg, i, p)))
        for i, p in enumerate(policies)
    ]
    return sim, agents, [sim, *agents, *([feed] if feed else [])]


def run_in_process(
    cfg: LaunchConfig, policies: list[str], episodes: int, log: EpisodeLog, timeout_s: float | None = None,
    extra_listeners: int = 0,
) -> bool:
    """Run the graph on one executor in this process; True if ``episodes`` finished (0 = until Ctrl-C).

    rclpy must be initialised by the caller.
    """
    from medc_common.executors import make_executor, running, spin_once_alive

    sim, _, nodes = build_graph(cfg, policies, episodes, extra_listeners=extra_listeners)
    sim.episode_listeners.append(lambda r: log.add(r.episode, r.length, r.success))
    executor = make_executor()
    for node in nodes:
        executor.add_node(node)
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        while running() and not sim.finished:
            if not spin_once_alive(executor, 0.1):
                return False
            if deadline is not None and time.monotonic() > deadline:
                return False
        if sim.finished and extra_listeners:
            # A reader in another process (the recorder) gets the last results only while their
            # reliable writers live: linger as medc-sim does before the nodes go.
            linger = time.monotonic() + RECORDER_LINGER_S
            while running() and time.monotonic() < linger and spin_once_alive(executor, 0.05):
                pass
        return sim.finished
    finally:
        executor.shutdown()
        for node in nodes:
            node.destroy_node()


def _child_env() -> dict[str, str]:
    env = interfaces_env()
    env["PYTHONUNBUFFERED"] = "1"
    return env


def _stop(children: list[subprocess.Popen], grace_s: float = 5.0) -> None:
    """SIGINT every child still running (rclpy's clean shutdown), then kill any that hangs."""
    for child in children:
        if child.poll() is None:
            child.send_signal(signal.SIGINT)
    deadline = time.monotonic() + grace_s
    for child in children:
        try:
            child.wait(max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()


def run_processes(
    cfg: LaunchConfig, policies: list[str], episodes: int, log: EpisodeLog, timeout_s: float | None = None,
    extra_listeners: int = 0,
) -> bool:
    """Run every node as its own process; this process listens to the episode status.

    rclpy must be initialised by the caller. True if ``episodes`` finished (0 = until Ctrl-C).
    """
    import rclpy
    from medc_common import contract
    from medc_common.auth_node import NodeAuth
    from medc_common.executors import running, spin_once_alive
    from medc_common.health import run_id
    from medc_interfaces.msg import EpisodeStatus
    from rclpy.executors import SingleThreadedExecutor

    monitor = rclpy.create_node("medc_launch", namespace=cfg.namespace)
    executor = SingleThreadedExecutor()
    executor.add_node(monitor)
    seen: set[int] = set()

    # Under a mission key (MEDC_AUTH_KEY_FILE) only the driver's signed results count.
    results_auth = NodeAuth("", run_id())
    results_topic = contract.results_topic(cfg.namespace)

    def on_status(msg: EpisodeStatus) -> None:
        if not results_auth.admit(msg, results_topic, "result"):
            return
        if msg.done and msg.episode not in seen:
            seen.add(msg.episode)
            log.add(msg.episode, msg.episode_length, msg.success)

    # The results topic keeps every episode's result for readers that start late or fall behind.
    monitor.create_subscription(
        EpisodeStatus, contract.results_topic(cfg.namespace), on_status, contract.RESULTS_QOS
    )
    bindir = Path(sys.executable).parent
    env = _child_env()
    # The monitor must be matched before the first step and before the simulator exits: the
    # recorder, a results reader as well, must not stand in for it (medc_sim.start_gate).
    sim_params = sim_parameters(cfg, episodes, extra_listeners, results_readers=1 + extra_listeners)
    ns = cfg.namespace
    commands = [[str(bindir / "medc-sim"), *ros_args("medc_sim", sim_params, ns)]]
    commands += [
        [str(bindir / "medc-agent"), *ros_args(agent_node_name(i), agent_parameters(cfg, i, p), ns)]
        for i, p in enumerate(policies)
    ]
    if cfg.registry.get("enabled"):
        params = dict(cfg.registry.get("params") or {})
        commands.append([str(bindir / "medc-bridge"), *ros_args("medc_bridge", params, ns)])
    # Own sessions: Ctrl-C reaches the launcher only, which then stops the children in order.
    children = [subprocess.Popen(c, env=env, start_new_session=True) for c in commands]
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    try:
        while running():
            if not spin_once_alive(executor, 0.1):
                return False
            if episodes and len(seen) >= episodes:
                if extra_listeners:  # the recorder: let the last moves reach it (RECORDER_LINGER_S)
                    linger = time.monotonic() + RECORDER_LINGER_S
                    while running() and time.monotonic() < linger and spin_once_alive(executor, 0.05):
                        pass
                return True
            if any(c.poll() not in (None, 0) for c in children):
                failed = [" ".join(c.args[:1]) for c in children if c.poll() not in (None, 0)]
                print(f"medc-launch: node process failed: {failed}", file=sys.stderr)
                return False
            if deadline is not None and time.monotonic() > deadline:
                return False
        return False
    finally:
        _stop(children)
        executor.shutdown()
        monitor.destroy_node()


def policy_from_cwd(policy: str | None, cwd: Path | None = None) -> str | None:
    """``--policy`` as given on the command line: a classical controller's name unchanged, a path
    made absolute from the current directory (not the repository root, as config-file paths are).

    Raises:
        ValueError: the path does not exist; the message says where a relative one was looked for.
    """
    if policy is None or _controller(policy):
        return policy
    cwd = Path.cwd() if cwd is None else cwd
    path = Path(policy).expanduser()
    absolute = path if path.is_absolute() else cwd / path
    if not absolute.exists():
        where = (
            "" if path.is_absolute() else f" (a relative --policy is taken from the current directory, {cwd})"
        )
        raise ValueError(
            f"--policy {policy!r}: {absolute} does not exist{where}; pass a bundle file or folder, "
            f"or a classical controller: {', '.join(_controllers())}"
        )
    return str(absolute)


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``medc-launch`` (see the module docstring)."""
    from medc_training.console import QUIET_HELP, HelpFormatter, epilog

    parser = argparse.ArgumentParser(prog="medc-launch", description=__doc__.split("\n\n")[0],
                                     formatter_class=HelpFormatter, epilog=epilog(__doc__))
    parser.add_argument("--config", help=f"launch YAML (default {DEFAULT_CONFIG})")
    parser.add_argument(
        "--episodes", type=int, default=0, help="run N episodes, then print a JSON line and exit"
    )
    parser.add_argument("--in-process", action="store_true", help="all nodes in this process, one executor")
    parser.add_argument("--seed", type=int, help="override the config's seed")
    parser.add_argument("--policy", help="override the config's policy (bundle file or folder, relative to "
                        f"the current directory, or a classical controller: {', '.join(_controllers())})")
    parser.add_argument("--agents", type=int, help="override the config's number of agents")
    parser.add_argument("--sensing", help="override the config's sensing preset (paper-simple, realistic)")
    parser.add_argument("--namespace", help="override the config's namespace (/medc): the ROS namespace "
                        "of every node, so the whole team's topics and services move under it")
    parser.add_argument("--timeout", type=float, help="give up after this many seconds")
    parser.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    parser.add_argument("--record", metavar="FILE.mcap",
                        help="record every topic of the team to this MCAP file (rosbag2 layout; medc-record)")
    parser.add_argument("--overwrite", action="store_true",
                        help="with --record: replace FILE.mcap if it exists (a link is replaced, never "
                             "written through)")
    parser.add_argument("--listeners", type=int, default=0, metavar="N",
                        help="the first step waits (up to 30 s) for N more readers of the episode status "
                             "and results topics: tools started on their own (e.g. joined to an isolated "
                             "mission with nsenter) that must hear the whole run")
    parser.add_argument("--foxglove", nargs="?", type=int, const=8765, default=None, metavar="PORT",
                        help="serve a live view to Foxglove on ws://127.0.0.1:PORT (default port 8765)")
    parser.add_argument("--foxglove-clients", type=int, default=DEFAULT_MAX_CLIENTS, metavar="N",
                        help="with --foxglove: connections the live view serves at once")
    parser.add_argument("--foxglove-origin", action="append", default=[], metavar="ORIGIN",
                        help="with --foxglove: also serve web pages of this origin (repeatable; the live "
                             "view refuses any page not served by this machine)")
    parser.add_argument("--authenticate", action="store_true",
                        help="sign every status, reading, move and declaration with a mission key and "
                             "use only verified ones (docs/security.md); default: the open mode")
    parser.add_argument("--key-file", metavar="FILE",
                        help="with --authenticate: the mission key file to use, written (0600) with a new "
                             "key when it does not exist; default: a new key in a private folder removed "
                             "at the end")
    return parser


def _check_args(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse (``parser.error``: usage, status 2) what argparse alone lets through: a negative
    ``--episodes`` or ``--listeners``, an option given without the one it qualifies, too few Foxglove
    connections."""
    if args.episodes < 0:
        parser.error("--episodes must be >= 0")
    if args.listeners < 0:
        parser.error(f"--listeners must be >= 0, got {args.listeners}")
    if args.overwrite and args.record is None:
        parser.error("--overwrite is only used with --record FILE.mcap")
    if args.foxglove_origin and args.foxglove is None:
        parser.error("--foxglove-origin is only used with --foxglove")
    if args.foxglove_clients < 1:
        parser.error(f"--foxglove-clients must be at least 1, got {args.foxglove_clients}")
    if args.key_file is not None and not args.authenticate:
        parser.error("--key-file is only used with --authenticate")


def issue_key(key_file: str | None, tmp_dir: Path) -> Path:
    """The mission key file of an authenticated run: ``key_file`` when it holds a usable key, a new
    key written to it (0600) when it does not exist, else a new key in ``tmp_dir`` (a 0700 folder of
    this run). AuthError (a ValueError) for a file that cannot be used."""
    from medc_common import auth

    if key_file is None:
        return auth.write_key_file(tmp_dir / "mission.key")
    path = Path(key_file).expanduser()
    if os.path.lexists(path):  # False for a name too long: write_key_file then says so
        auth.load_key_file(path)  # refuses a link, a shared or malformed file
        return path.resolve()
    return auth.write_key_file(path).resolve()


def main(argv: list[str] | None = None) -> int:
    """Console script ``medc-launch`` (see the module docstring)."""
    parser = build_parser()
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    _check_args(parser, args)
    try:
        cfg = load_config(args.config, seed=args.seed, policy=policy_from_cwd(args.policy),
                          agents=args.agents, sensing=args.sensing, namespace=args.namespace)
        policies = resolve_policies(cfg)
    except ValueError as exc:
        print(f"medc-launch: {exc}", file=sys.stderr)
        return 2
    require_interfaces()  # may re-execute this process: before any key is issued
    key_dir = tempfile.TemporaryDirectory(prefix="medc-auth-") if args.authenticate else None
    try:
        if key_dir is not None:
            from medc_common.auth import KEY_FILE_ENV

            # Every node reads it (its auth_key_file parameter's fallback); children inherit it.
            os.environ[KEY_FILE_ENV] = str(issue_key(args.key_file, Path(key_dir.name)))
    except ValueError as exc:
        key_dir.cleanup()
        print(f"medc-launch: {exc}", file=sys.stderr)
        return 2
    try:
        return _run(args, cfg, policies)
    finally:
        if key_dir is not None:
            key_dir.cleanup()


def _run(args: argparse.Namespace, cfg: LaunchConfig, policies: list[str]) -> int:
    """Start the recorder and the graph of ``cfg`` as ``args`` say; the exit status."""
    import rclpy
    from medc_common.executors import install_stop_handlers, stop_requested
    from rclpy.executors import ExternalShutdownException
    from rclpy.signals import SignalHandlerOptions

    from medc_bringup.recorder import start_recorder, stop_recorder

    log = EpisodeLog(quiet=args.quiet)
    try:
        recorder = start_recorder(cfg, args.record, args.foxglove, quiet=args.quiet, overwrite=args.overwrite,
                                  foxglove_clients=args.foxglove_clients,
                                  foxglove_origins=tuple(args.foxglove_origin))
    except ValueError as exc:
        print(f"medc-launch: {exc}", file=sys.stderr)
        return 2
    recording: dict[str, Any] | None = None
    recorder_failed = False
    rclpy.init(args=["medc-launch"], signal_handler_options=SignalHandlerOptions.NO)
    # Ctrl-C and SIGTERM only ask the run loop to end (seen within 0.1 s): no exception lands
    # between an episode's line and its record, and the nodes are stopped in order.
    install_stop_handlers()
    start = time.monotonic()
    ok = False
    interrupted = False
    run = run_in_process if args.in_process else run_processes
    try:
        ok = run(cfg, policies, args.episodes, log, timeout_s=args.timeout,
                 extra_listeners=(recorder is not None) + args.listeners)
        interrupted = not ok and stop_requested()
    except ExternalShutdownException:
        interrupted = True
    finally:
        rclpy.try_shutdown()
        if recorder is not None:
            recording = stop_recorder(recorder)
            if recorder.returncode != 0 or recording is None:
                # Its own error (a busy Foxglove port, an unwritable file) is on stderr already.
                print(f"medc-launch: the recorder failed (exit status {recorder.returncode}); "
                      "see its message above", file=sys.stderr)
                recorder_failed = True
    if args.episodes or interrupted:
        print(
            json.dumps(
                log.summary(
                    seed=cfg.seed,
                    agents=cfg.agents,
                    mode=cfg.mode,
                    end_on=cfg.end_on,
                    in_process=args.in_process,
                    wall_s=round(time.monotonic() - start, 3),
                    config=asdict(cfg) | {"policies": policies},
                    authenticated=args.authenticate,
                    **({"recording": recording} if recorder is not None else {}),
                )
            )
        )
    if (not ok and not interrupted) or recorder_failed:  # a node failed, --timeout ran out, no recording
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
