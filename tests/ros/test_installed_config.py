"""Config files come from the installed package (share/<pkg>/config, found through the ament
index), else the source tree; a relative --policy is taken from the current directory; the bridge
removes the temporary bundle folder it made."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2] / "ros_ws" / "src"


@pytest.mark.parametrize(
    ("package", "name"),
    [("medc_bringup", "launch.yaml"), ("medc_sim", "sim.yaml"), ("medc_agents", "agent.yaml"),
     ("medc_registry", "bridge.yaml")],
)
def test_setup_installs_the_config_files(package, name, monkeypatch):
    import setuptools

    seen: dict = {}
    monkeypatch.setattr(setuptools, "setup", lambda **kw: seen.update(kw))
    monkeypatch.chdir(SRC / package)
    runpy.run_path(str(SRC / package / "setup.py"), run_name="__main__")
    files = dict(seen["data_files"])
    assert f"config/{name}" in files[f"share/{package}/config"]


def test_config_file_prefers_the_ament_index_then_the_source_tree(tmp_path, monkeypatch):
    from medc_common.share import config_file

    assert config_file("medc_bringup", "launch.yaml").is_file()  # found somewhere: source tree at least
    prefix = tmp_path / "install"
    (prefix / "share" / "ament_index" / "resource_index" / "packages").mkdir(parents=True)
    (prefix / "share" / "ament_index" / "resource_index" / "packages" / "medc_bringup").write_text("")
    installed = prefix / "share" / "medc_bringup" / "config" / "launch.yaml"
    installed.parent.mkdir(parents=True)
    installed.write_text("seed: 7\n")
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(prefix))
    assert config_file("medc_bringup", "launch.yaml") == installed
    monkeypatch.setenv("AMENT_PREFIX_PATH", str(tmp_path / "empty"))
    monkeypatch.setattr(sys, "prefix", str(tmp_path / "no-venv"))
    found = config_file("medc_bringup", "launch.yaml")
    assert found.is_file() and found.parts[-3:] == ("medc_bringup", "config", "launch.yaml")


def test_relative_policy_is_taken_from_the_current_directory(tmp_path, monkeypatch, bundles):
    from medc_bringup.launcher import policy_from_cwd

    here = tmp_path / "work"
    (here / "mine").mkdir(parents=True)
    (here / "mine" / "team.safetensors").write_bytes(bundles["a"].read_bytes())
    monkeypatch.chdir(here)
    assert policy_from_cwd("mine/team.safetensors") == str(here / "mine" / "team.safetensors")
    assert policy_from_cwd("greedy") == "greedy" and policy_from_cwd(None) is None
    with pytest.raises(ValueError, match="taken from the current directory") as err:
        policy_from_cwd("models/team")
    assert str(here / "models" / "team") in str(err.value)


def test_launcher_says_where_a_relative_policy_was_looked_for(tmp_path, monkeypatch, capsys):
    from medc_bringup.launcher import main

    monkeypatch.chdir(tmp_path)
    assert main(["--policy", "no/such.safetensors", "--episodes", "1"]) == 2
    err = capsys.readouterr().err
    assert str(tmp_path / "no" / "such.safetensors") in err and "current directory" in err


@pytest.mark.ros
def test_bridge_removes_its_temporary_bundle_folder(rclpy_context, tmp_path):
    import rclpy
    from medc_registry.bridge_node import bridge_node_class

    bridge = bridge_node_class()(registry=object())
    own = Path(bridge.bridge.cache_dir)
    assert own.is_dir() and own.name.startswith("medc-bundles-")
    (own / "x.safetensors").write_bytes(b"x")
    bridge.destroy_node()
    assert not own.exists()
    given = tmp_path / "cache"
    bridge = bridge_node_class()(
        registry=object(), parameter_overrides=[rclpy.parameter.Parameter("cache_dir", value=str(given))]
    )
    bridge.destroy_node()
    assert given.is_dir()  # a cache the user named is theirs to keep
