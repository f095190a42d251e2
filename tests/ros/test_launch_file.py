"""medc_bringup/launch/medc.launch.py, for ``ros2 launch`` on a full ROS install: it compiles, loads
without launch/launch_ros (not installed here), names only the packages' installed console scripts
and parameter files, is installed with the package, and describes the team medc-launch starts.
tests/ros/test_two_teams.py runs the nodes it describes."""

from __future__ import annotations

import ast
import importlib.util
import runpy
from pathlib import Path

import pytest
import yaml
from ros_helpers import load_launch_file

SRC = Path(__file__).resolve().parents[2] / "ros_ws" / "src"
LAUNCH_FILE = SRC / "medc_bringup" / "launch" / "medc.launch.py"


def setup_kwargs(package: str, monkeypatch) -> dict:
    """What ``setup()`` of ``package``'s setup.py is called with."""
    import setuptools

    seen: dict = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kw: seen.update(kw))
    monkeypatch.chdir(SRC / package)
    runpy.run_path(str(SRC / package / "setup.py"), run_name="__main__")
    return seen


def test_it_compiles_and_imports_launch_only_when_run():
    tree = ast.parse(LAUNCH_FILE.read_text(), str(LAUNCH_FILE))
    compile(tree, str(LAUNCH_FILE), "exec")
    functions = {n.name for n in tree.body if isinstance(n, ast.FunctionDef)}
    assert {"generate_launch_description", "team_nodes"} <= functions
    top = [n for n in tree.body if isinstance(n, ast.Import | ast.ImportFrom)]
    assert [getattr(n, "module", None) for n in top] == ["__future__"], "launch imported at load time"
    inside = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    assert {"launch", "launch.actions", "launch.substitutions", "launch_ros.actions"} <= inside
    module = load_launch_file()  # launch_ros is not installed here: loading must not need it
    assert callable(module.generate_launch_description)
    if importlib.util.find_spec("launch_ros") is None:
        # (with ros_ws/src/medc_bringup on PYTHONPATH, its launch/ folder passes for a package:
        # an ImportError either way)
        with pytest.raises(ImportError, match="launch"):
            module.generate_launch_description()


def test_executables_and_parameter_files_are_the_installed_ones(monkeypatch):
    module = load_launch_file()
    assert set(module.EXECUTABLES) == {"medc_sim", "medc_agents", "medc_registry"}
    for package, (executable, params_file) in module.EXECUTABLES.items():
        kwargs = setup_kwargs(package, monkeypatch)
        scripts = {line.split("=")[0].strip() for line in kwargs["entry_points"]["console_scripts"]}
        assert executable in scripts, (package, executable, scripts)
        assert (SRC / package / "config" / params_file).is_file()
        assert f"config/{params_file}" in dict(kwargs["data_files"])[f"share/{package}/config"]
        # setup.cfg puts the console scripts in lib/<package>, where launch_ros looks for them.
        assert f"install_scripts=$base/lib/{package}" in (SRC / package / "setup.cfg").read_text()
    bringup = setup_kwargs("medc_bringup", monkeypatch)
    assert "launch/medc.launch.py" in dict(bringup["data_files"])["share/medc_bringup/launch"]


def test_it_describes_the_team_medc_launch_starts(bundles, tmp_path):
    from medc_bringup.launcher import agent_parameters, load_config, resolve_policies, sim_parameters

    module = load_launch_file()
    config = tmp_path / "launch.yaml"
    config.write_text(f"walls: 1\nmax_steps: 20\npolicy: {bundles['a']}\n"
                      "registry: {enabled: false, params: {chain: embedded}}\n")
    nodes = module.team_nodes({"namespace": "/team2", "config": str(config), "agents": "2", "seed": "5",
                               "episodes": "3", "registry": "true"})
    assert [(n["package"], n["executable"], n["name"]) for n in nodes] == [
        ("medc_sim", "medc-sim", "medc_sim"), ("medc_agents", "medc-agent", "medc_agent_0"),
        ("medc_agents", "medc-agent", "medc_agent_1"), ("medc_registry", "medc-bridge", "medc_bridge")]
    assert {n["namespace"] for n in nodes} == {"/team2"}
    assert [n.get("ends_launch", False) for n in nodes] == [True, False, False, False]
    cfg = load_config(config, agents=2, seed=5, namespace="/team2")
    policies = resolve_policies(cfg)
    assert nodes[0]["parameters"][1] == sim_parameters(cfg, 3)
    expected = [agent_parameters(cfg, i, p) for i, p in enumerate(policies)]
    assert [n["parameters"][1] for n in nodes[1:3]] == expected
    assert nodes[3]["parameters"][1] == {"chain": "embedded"}
    for node in nodes:
        params_file = Path(node["parameters"][0])
        assert params_file.is_file() and params_file.parent.name == "config"
        # The file's node key applies to this node in any namespace.
        assert set(yaml.safe_load(params_file.read_text())) <= {"/**", f"/**/{node['name']}"}
    default = module.team_nodes({"config": str(config)})
    assert {n["namespace"] for n in default} == {"/medc"} and len(default) == 4  # 3 agents, no bridge
    assert not default[0]["ends_launch"]


@pytest.mark.parametrize(("values", "message"), [
    ({"agents": "three"}, "agents:='three' is not a whole number"),
    ({"episodes": "-1"}, "episodes:=-1 must be >= 0"),
    ({"registry": "maybe"}, "registry:='maybe' must be true or false"),
    ({"namespace": "team 2"}, "not a valid ROS namespace"),
    ({"policy": "no/such.safetensors"}, "a relative --policy is taken from the current directory"),
])
def test_bad_launch_arguments_are_refused_with_the_reason(values, message):
    module = load_launch_file()
    with pytest.raises(ValueError, match=message):
        module.team_nodes({"policy": "greedy", **values})
