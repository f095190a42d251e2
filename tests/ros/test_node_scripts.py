"""The node console scripts refuse bad parameters with a clear message and exit code 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent


@pytest.mark.ros
@pytest.mark.parametrize(
    ("script", "param", "message"),
    [
        ("medc-agent", "agent_id:=agent_7", "unknown agent id 'agent_7'"),
        ("medc-sim", "mode:=fast", "mode must be 'stepped' or 'realtime'"),
        ("medc-sim", "walls:=99", "walls must be an integer"),
    ],
)
def test_bad_parameter_is_refused_clearly(script, param, message):
    out = subprocess.run(
        [str(BIN / script), "--ros-args", "-p", param], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 2
    assert message in out.stderr
