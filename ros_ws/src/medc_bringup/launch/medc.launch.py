"""The MEDC team for a full ROS 2 install: ``ros2 launch medc_bringup medc.launch.py``.

    ros2 launch medc_bringup medc.launch.py policy:=/path/to/team.safetensors
    ros2 launch medc_bringup medc.launch.py policy:=greedy agents:=3 grid:=30 episodes:=20
    ros2 launch medc_bringup medc.launch.py namespace:=/team2 seed:=7 policy:=/path/to/team.safetensors
    ros2 launch medc_bringup medc.launch.py registry:=true policy:=/path/to/team.safetensors

It starts what ``medc-launch`` starts, with the same files and the same rules: the launch config
(``share/medc_bringup/config/launch.yaml``, or ``config:=FILE``) completed from the policy bundle's
manifest and checked against it by :mod:`medc_bringup.launcher`, the simulator (``medc-sim``), one
agent node per agent (``medc-agent``) and, with ``registry:=true``, the registry bridge
(``medc-bridge``), each with its package's installed parameter file (``share/<package>/config``,
found through the ament index) and then the values of the launch config. Every node is created in
``namespace`` (default ``/medc``): all MEDC names are relative to it, so ``namespace:=/team2``
moves the whole team. With ``episodes:=N`` the launch ends when the simulator has played N.

Nothing of ``launch``/``launch_ros`` is imported until :func:`generate_launch_description` runs, so
:func:`team_nodes` (what it starts) can be read and tested where they are not installed.
"""

from __future__ import annotations

#: Launch arguments: name -> (default, description). An empty default: the launch config's value.
LAUNCH_ARGUMENTS = {
    "namespace": ("/medc", "ROS namespace of every node of the team (its topics and services move with it)"),
    "config": ("", "launch YAML (default: the installed share/medc_bringup/config/launch.yaml)"),
    "policy": ("", "bundle file or folder (relative to the current directory), or a classical controller: "
                   "gradient, greedy, infotaxis, infotaxis-exact, space-aware, infotaxis-2step, "
                   "team-infotaxis, team-space-aware; empty: the launch config's"),
    "agents": ("", "number of agents; empty: the launch config's, else the bundle manifest's"),
    "grid": ("", "grid side in cells; empty: the launch config's, else the bundle manifest's"),
    "seed": ("", "environment seed; empty: the launch config's"),
    "episodes": ("0", "end the launch after this many episodes (0: run until Ctrl-C)"),
    "registry": ("false", "also start the registry bridge (medc-bridge); its parameters: the launch "
                          "config's registry.params over share/medc_registry/config/bridge.yaml"),
}

#: The nodes' packages: package -> (console script, parameter file in share/<package>/config).
EXECUTABLES = {
    "medc_sim": ("medc-sim", "sim.yaml"),
    "medc_agents": ("medc-agent", "agent.yaml"),
    "medc_registry": ("medc-bridge", "bridge.yaml"),
}


def _int_or_none(values: dict[str, str], name: str) -> int | None:
    text = str(values.get(name, "")).strip()
    if not text:
        return None
    try:
        return int(text)
    except ValueError:
        raise ValueError(f"launch argument {name}:={text!r} is not a whole number") from None


def _flag(values: dict[str, str], name: str) -> bool:
    text = str(values.get(name, "false")).strip().lower()
    if text not in ("true", "false", "1", "0"):
        raise ValueError(f"launch argument {name}:={text!r} must be true or false")
    return text in ("true", "1")


def _node(package: str, name: str, namespace: str, params: dict) -> dict:
    from medc_common.share import config_file

    executable, params_file = EXECUTABLES[package]
    return {"package": package, "executable": executable, "name": name, "namespace": namespace,
            "parameters": [str(config_file(package, params_file)), params]}


def _policy_root():
    """Where a relative policy of the launch config is taken from: the repository root of a
    checkout, else (an installed package) the current directory."""
    from pathlib import Path

    from medc_common.ros_env import repo_root

    try:
        return repo_root()
    except RuntimeError:
        return Path.cwd()


def team_nodes(values: dict[str, str]) -> list[dict]:
    """The nodes the launch starts for the launch argument ``values`` (names of LAUNCH_ARGUMENTS;
    a missing one takes its default): dicts with ``package``, ``executable``, ``name``,
    ``namespace`` and ``parameters`` (the package's installed parameter file, then a dict over it),
    and ``ends_launch`` (the simulator when ``episodes`` > 0).

    Raises:
        ValueError: a bad argument, a launch config or policy medc-launch would refuse (its message).
    """
    from medc_bringup.launcher import (
        agent_parameters,
        load_config,
        policy_from_cwd,
        resolve_policies,
        sim_parameters,
    )
    from medc_common.contract import agent_node_name

    values = {name: default for name, (default, _) in LAUNCH_ARGUMENTS.items()} | dict(values)
    episodes = _int_or_none(values, "episodes") or 0
    if episodes < 0:
        raise ValueError(f"launch argument episodes:={episodes} must be >= 0")
    cfg = load_config(values["config"] or None, namespace=values["namespace"] or None,
                      policy=policy_from_cwd(values["policy"] or None), agents=_int_or_none(values, "agents"),
                      grid=_int_or_none(values, "grid"), seed=_int_or_none(values, "seed"))
    policies = resolve_policies(cfg, _policy_root())
    sim = _node("medc_sim", "medc_sim", cfg.namespace, sim_parameters(cfg, episodes))
    sim["ends_launch"] = episodes > 0
    nodes = [sim] + [_node("medc_agents", agent_node_name(i), cfg.namespace, agent_parameters(cfg, i, p))
                     for i, p in enumerate(policies)]
    if _flag(values, "registry"):
        bridge = dict(cfg.registry.get("params") or {})
        nodes.append(_node("medc_registry", "medc_bridge", cfg.namespace, bridge))
    return nodes


def generate_launch_description():
    """The launch description: the arguments, and the nodes of :func:`team_nodes` (launch_ros)."""
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction, Shutdown
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import Node

    def nodes(context):
        values = {name: LaunchConfiguration(name).perform(context) for name in LAUNCH_ARGUMENTS}
        actions = []
        for spec in team_nodes(values):
            ends = [Shutdown(reason="the simulator played its episodes")] if spec.get("ends_launch") else None
            actions.append(Node(package=spec["package"], executable=spec["executable"], name=spec["name"],
                                namespace=spec["namespace"], parameters=spec["parameters"], output="screen",
                                on_exit=ends))
        return actions

    arguments = [DeclareLaunchArgument(name, default_value=default, description=text)
                 for name, (default, text) in LAUNCH_ARGUMENTS.items()]
    return LaunchDescription([*arguments, OpaqueFunction(function=nodes)])
