"""Every console script of the house answers ``--help``: its usage and parameters, exit status 0, and no
node is started (docs/ros-reference.md, "Nodes and parameters"). The entry points are read from the setup.py
files and training/pyproject.toml (tests/test_layout.py's reader), so a new script is covered at once;
each runs through its ``main`` in a fresh interpreter, as the installed script would."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from ros_domain import claim_domain
from test_layout import _entry_points

#: Node scripts: their help lists the ROS parameters their nodes declare.
NODE_SCRIPTS = {"medc-sim": ("medc_sim.simulator",),
                "medc-agent": ("medc_agents.node", "medc_agents.estimate"),
                "medc-bridge": ("medc_registry.bridge_node",)}


def _scripts() -> list[tuple[list[str], str]]:
    """(argv, "module:function") of every console script, and ``medc-bench <name>`` of the bench group."""
    out = []
    for _, group, name, target in _entry_points():
        if group == "console_scripts":
            out.append(([name, "--help"], target))
        elif group == "medc_bench":
            out.append((["medc-bench", name, "--help"], target))
    return out


SCRIPTS = _scripts()


def test_every_console_script_is_covered():
    names = {argv[0] for argv, _ in SCRIPTS}
    assert {"medc-sim", "medc-agent", "medc-bridge", "medc-launch", "medc-registry", "medc-train"} <= names


@pytest.mark.parametrize(("argv", "target"), SCRIPTS, ids=[" ".join(a[:-1]) for a, _ in SCRIPTS])
def test_help_exits_0_without_starting_a_node(argv, target):
    module, _, function = target.partition(":")
    code = (f"import sys; sys.argv = {argv!r}; from {module} import {function} as main; "
            "sys.exit(main())")
    # A domain of its own: a node started by mistake would not meet anyone else's graph.
    env = {**os.environ, "ROS_DOMAIN_ID": str(claim_domain())}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=180, env=env)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout + out.stderr
    assert "usage" in text.lower() and "Traceback" not in text
    assert "[INFO]" not in text and "[WARN]" not in text  # a node that started would log its start
    if argv[0] in NODE_SCRIPTS:
        from medc_common.cli_help import declared_parameters

        params = declared_parameters(*NODE_SCRIPTS[argv[0]])
        assert len(params) >= 8
        for name, default, _ in params:
            assert f"  {name} (default {default})" in out.stdout
