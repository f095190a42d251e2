"""The node console scripts refuse bad parameters with a clear message and exit code 2."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BIN = Path(sys.executable).parent
TEAM = str(Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors")
#: A team member trained in the benchmark's world with domain randomisation (its manifest says so).
RANDOMISED = str(Path(__file__).resolve().parents[2] / "docs" / "reproduction" / "learned-team"
                 / "main-posterior-dr" / "medc-s0" / "policy.safetensors")


@pytest.mark.ros
@pytest.mark.parametrize(
    ("script", "params", "message"),
    [
        ("medc-agent", ["agent_id:=agent_7", f"policy:={TEAM}"], "unknown agent id 'agent_7'"),
        # An agent never idles without a policy: it refuses to start, saying why.
        ("medc-agent", ["agent_id:=agent_1"], "no policy bundle: start the agent with -p policy:="),
        ("medc-agent", ["policy:=/no/such/bundle.safetensors"], "is not an existing file"),
        ("medc-agent", [f"policy:={TEAM}", "grid:=30", "observation:=maps"], "refused, not starting"),
        ("medc-sim", ["mode:=fast"], "mode must be 'stepped' or 'realtime'"),
        ("medc-sim", ["walls:=99"], "walls must be an integer"),
        ("medc-sim", ["sensing:=noisy"], "unknown sensing preset 'noisy'"),
        ("medc-agent", [f"policy:={TEAM}", "sensing:=noisy"], "sensing must be one of"),
        # The shipped team was trained under paper-simple (its manifest names no sensing).
        ("medc-agent", [f"policy:={TEAM}", "sensing:=realistic"],
         "trained under the sensing model 'paper-simple', but this team senses with 'realistic'"),
        ("medc-agent", [f"policy:={RANDOMISED}", "sensing:=realistic"],
         "trained in the 'radbench' world with transmission_max=0.3, efficiency_spread=0.3"),
        # The benchmark's world: what does not apply there is refused, saying what to set.
        ("medc-sim", ["world:=radbench", "sensing:=realistic", "grid:=25"], "grids of 20 or 30 cells"),
        ("medc-agent", [f"policy:={TEAM}", "world:=radbench"], "set sensing realistic"),
        ("medc-agent", [f"policy:={TEAM}", "endgame_tau:=1.5"], "endgame_tau must be a number in (0, 1]"),
    ],
)
def test_bad_parameter_is_refused_clearly(script, params, message):
    args = [str(BIN / script), "--ros-args"]
    for param in params:
        args += ["-p", param]
    out = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert message in out.stderr and "Traceback" not in out.stderr
