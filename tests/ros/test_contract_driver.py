"""A driver written from docs/ros-reference.md alone (tests/ros/contract_driver.py: its own ENU
world, walls and sensor model) runs the shipped team as three medc-agent processes started from
the bundle alone. The driver is restarted mid-run and sends one mis-stamped reading: the team
keeps stepping, every move is the policy's on the driver's world, and the mistake and the
restart each appear once per agent in the logs and on /diagnostics."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

HERE = Path(__file__).resolve().parent
TEAM = HERE.parents[1] / "models" / "team" / "A3W2.safetensors"
BIN = Path(sys.executable).parent
DRIVER = HERE / "contract_driver.py"
SIZE = 13


def test_the_driver_uses_only_the_documented_contract():
    import ast

    imported = set()
    for node in ast.walk(ast.parse(DRIVER.read_text())):
        if isinstance(node, ast.Import):
            imported |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported.add(node.module.split(".")[0])
    # ROS client library, standard messages, the project's message package; nothing of its code.
    assert imported <= {"__future__", "argparse", "json", "math", "secrets", "sys", "time", "numpy", "rclpy",
                        "builtin_interfaces", "geometry_msgs", "nav_msgs", "medc_interfaces"}, imported


@pytest.mark.parametrize("grid, walls", [(13, 2), (10, 1), (30, 2)])
def test_the_documented_sensor_model_is_the_environments_bit_for_bit(grid, walls):
    """docs/ros-reference.md's sensor model, as the driver implements it, equals
    expected_rate_from_sources on every source-sensor pair of several layouts."""
    from contract_driver import rate
    from medc_training.envs.target_localization import expected_rate_from_sources, generate_layouts

    lay = generate_layouts(3, grid, walls, 1, torch.Generator().manual_seed(grid), torch.device("cpu"))
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    cells_rc = np.stack([rows.ravel(), cols.ravel()], 1)
    for b in range(3):
        walls_rc = lay["walls"][b].numpy()
        free = cells_rc[~walls_rc[cells_rc[:, 0], cells_rc[:, 1]]]
        positions = torch.from_numpy(free).unsqueeze(0)
        expected = expected_rate_from_sources(positions, positions[0], lay["walls"][b:b + 1])[0].numpy()
        walls_ij = walls_rc[::-1].T  # [i, j]: i = col, j = H - 1 - row
        sensors_ij = np.stack([free[:, 1], grid - 1 - free[:, 0]], 1)
        for m, (r, c) in enumerate(free):
            got = rate(walls_ij, (int(c), int(grid - 1 - r)), sensors_ij)
            assert np.array_equal(got, expected[:, m]), (b, r, c)


@pytest.mark.parametrize("grid, walls", [(13, 2), (10, 2), (18, 4)])
def test_the_documented_realistic_line_of_sight_is_the_environments(grid, walls):
    """docs/ros-reference.md's realistic sensor model (a wall cell on the segment between the centres blocks
    it), as the driver implements it cell by cell in float64, blocks exactly the pairs the
    environment's rectangle rule blocks, and gives the same factor 1 / (1 + d^2) elsewhere, segments
    that only touch a wall corner (open) included."""
    from contract_driver import realistic_factor
    from medc_training.envs.target_localization import generate_layouts
    from medc_training.envs.tl_sensing import SENSING_PRESETS, geometric_factor

    model = SENSING_PRESETS["realistic"]
    lay = generate_layouts(3, grid, walls, 1, torch.Generator().manual_seed(grid), torch.device("cpu"))
    rows, cols = np.meshgrid(np.arange(grid), np.arange(grid), indexing="ij")
    cells_rc = np.stack([rows.ravel(), cols.ravel()], 1)
    blocked = grazing = pairs = 0
    for b in range(3):
        walls_rc = lay["walls"][b].numpy()
        free = cells_rc[~walls_rc[cells_rc[:, 0], cells_rc[:, 1]]]
        positions = torch.from_numpy(free).unsqueeze(0)
        expected = geometric_factor(model, positions, positions[0], lay["walls"][b:b + 1])[0].numpy()
        walls_ij = walls_rc[::-1].T
        sensors_ij = np.stack([free[:, 1], grid - 1 - free[:, 0]], 1)
        for m, (r, c) in enumerate(free):
            got, touch = realistic_factor(walls_ij, (int(c), int(grid - 1 - r)), sensors_ij)
            exp = expected[:, m]
            assert np.array_equal(got == 0, exp == 0), (b, r, c)
            assert np.allclose(got, exp, rtol=1e-6, atol=0), (b, r, c)
            blocked += int((got == 0).sum())
            grazing += int(touch.sum())
            pairs += len(got)
    assert blocked > 0 and grazing > 0, (blocked, grazing, pairs)


def _replayed_actions(steps: list[dict], policy) -> list[list[int]]:
    """The moves the team's policy makes on the driver's recorded world, rebuilt offline with the
    training environment's own memory and observation builder (no ROS code)."""
    from medc_training.envs.grid import action_deltas, move_mask, pad_blocked
    from medc_training.envs.tl_observation import ObservationSpec, TeamMemory, observe, parse_observation

    spec = parse_observation(policy.observation)
    memory = TeamMemory(ObservationSpec("maps", 0, True), 1, SIZE, "cpu")
    out, episode = [], None
    for s in steps:
        walls_ij = np.array(s["walls"], dtype=bool)
        walls = torch.from_numpy(np.ascontiguousarray(walls_ij.T[::-1])).unsqueeze(0)  # [1,row,col]
        positions = torch.tensor([[(SIZE - 1 - j, i) for i, j in s["cells"]]])
        readings = torch.tensor([s["readings"]], dtype=torch.float32)
        if s["step"] == 0 or s["episode"] != episode:
            memory.start(walls, positions, readings)
        else:
            memory.record(walls, positions, readings)
        episode = s["episode"]
        est, post = memory.source_maps(spec)
        obs = observe(spec, positions, memory.reading_map, memory.visit_map, walls.float(), est,
                      posterior_map=post)[0]
        mask = move_mask(positions, pad_blocked(walls), action_deltas("cpu"))[0]
        with torch.no_grad():
            out.append([int(a) for a in policy.act(obs, mask, greedy=True)])
    return out


@pytest.mark.timing
@pytest.mark.ros
def test_a_documented_driver_restarts_and_misstamps_and_the_team_goes_on(rclpy_context, tmp_path):
    from diagnostic_msgs.msg import DiagnosticStatus
    from medc_training.bundle import load_bundle
    from ros_helpers import DiagnosticsListener, run_contract_driver, stop_node_processes

    listener = DiagnosticsListener()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    agents, logs = [], [tmp_path / f"agent_{i}.log" for i in range(3)]
    start = time.monotonic()

    def run_driver(name: str, *extra: str) -> list[dict]:
        out = tmp_path / f"{name}.jsonl"
        run_contract_driver(listener, ["--out", str(out), *extra], timeout_s=300 - (time.monotonic() - start),
                            procs=agents, logs=logs)
        return [json.loads(line) for line in out.read_text().splitlines()]

    try:
        for i in range(3):  # started from the bundle alone: team size, grid, observation from its manifest
            agents.append(subprocess.Popen(
                [str(BIN / "medc-agent"), "--ros-args", "-p", f"agent_id:=agent_{i}",
                 "-p", f"policy:={TEAM}"],
                stdout=logs[i].open("w"), stderr=subprocess.STDOUT, env=env))
        first = run_driver("first", "--steps", "10", "--seed", "1", "--misstamp-step", "4")
        second = run_driver("second", "--steps", "10", "--seed", "2")  # restarted: episode 0 again
        # The stall (each agent's, while the mis-stamped step waited) and the restart (each agent's
        # event, at the second driver's first step) reach this listener.
        restarted = lambda: {d.hardware_id for d in listener.statuses()  # noqa: E731
                             if "the driver restarted" in d.message}
        listener.spin(60, lambda: len(restarted()) == 3, agents)
    finally:
        stop_node_processes(agents)
        listener.close()
    diagnostics = listener.statuses()

    # The team kept stepping through the restart: both drivers got every step answered.
    assert len(first) == len(second) == 10
    assert (first[0]["episode"], first[0]["step"]) == (second[0]["episode"], second[0]["step"]) == (0, 0)
    # ENU poses and a map with an offset origin: every move is valid in the driver's world, and is
    # exactly the policy's greedy move on that world (a mirrored frame would change them).
    steps = first + second
    assert all(all(s["valid"]) for s in steps)
    assert [s["actions"] for s in steps] == _replayed_actions(steps, load_bundle(TEAM))

    texts = [p.read_text() for p in logs]
    for i, text in enumerate(texts):
        assert "Traceback" not in text
        assert f"for agent_{i} of 3 agents on a 13x13 grid (observation ego6+estimate)" in text
        stalls = [line for line in text.splitlines() if "stalled:" in line]
        assert len(stalls) == 1, text[-3000:]  # the mis-stamped reading, once
        assert "waiting for: the reading of agent_1 stamped" in stalls[0]
        assert "+1.000 us from the status" in stalls[0]
        assert text.count("the driver restarted") == 1, text[-3000:]
    # The stall is published (and re-published by the 1 Hz heartbeat while it lasts) at level WARN,
    # under one name per agent; the restart is a WARN event, as in the log.
    warn = [d for d in diagnostics if d.level == DiagnosticStatus.WARN and "stalled:" in d.message
            and d.name.endswith(": team step")]
    assert sorted({d.name for d in warn}) == [f"medc_agent_{i}: team step" for i in range(3)]  # unique names
    assert all("reading of agent_1" in d.message for d in warn)
    assert len({(d.name, d.message) for d in warn}) == 3  # one stall per agent, re-published
    restarts = [d for d in diagnostics if "the driver restarted" in d.message]
    assert sorted(d.hardware_id for d in restarts) == ["agent_0", "agent_1", "agent_2"]
    assert all(d.level == DiagnosticStatus.WARN for d in restarts)
    # The team waited on nothing of its own, counted in the driver's re-sends (1 s apart) rather than
    # in seconds: the mis-stamped step was answered soon after the driver sent it again stamped
    # right, every other step (the restart's first included) within a few re-sends at most.
    resends = [s["resends"] for s in steps]
    assert resends[4] >= 1 and max(resends) <= 3, resends


@pytest.mark.timing
@pytest.mark.ros
def test_a_documented_driver_ends_each_episode_on_the_declaration_before_flying_its_step(rclpy_context,
                                                                                      tmp_path):
    """docs/ros-reference.md, "The driver loop": the driver processes every message already received before
    it flies a step's moves, so the team's declaration of step S (sent before its publisher's move)
    ends the episode after S moves, with step S's moves not flown."""
    from ros_helpers import DiagnosticsListener, run_contract_driver, stop_node_processes

    listener = DiagnosticsListener()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    logs = [tmp_path / f"agent_{i}.log" for i in range(3)]
    agents = []
    out, summary_path = tmp_path / "steps.jsonl", tmp_path / "summary.json"
    try:
        # A driver that ends episodes only on the declaration: docs/ros-guide.md, "Flying real UAVs".
        for i in range(3):
            agents.append(subprocess.Popen(
                [str(BIN / "medc-agent"), "--ros-args", "-p", f"agent_id:=agent_{i}",
                 "-p", f"policy:={TEAM}", "-p", "source_ends_episode:=false"],
                stdout=logs[i].open("w"), stderr=subprocess.STDOUT, env=env))
        args = ["--out", str(out), "--summary", str(summary_path), "--seed", "7", "--end-on", "declaration",
                "--episodes", "4", "--steps", "200", "--max-steps", "30"]
        text = run_contract_driver(listener, args, timeout_s=240, procs=agents, logs=logs)
    finally:
        stop_node_processes(agents)
        listener.close()
    summary = json.loads(summary_path.read_text())
    steps = [json.loads(line) for line in out.read_text().splitlines()]
    episodes, declarations = summary["episodes"], summary["declarations"]
    assert len(episodes) == 4, (episodes, text[-2000:])
    assert all(e["declared"] and e["success"] for e in episodes), (episodes, text[-2000:])
    assert [d["episode"] for d in declarations] == [0, 1, 2, 3]
    assert all(d["right"] and d["mass"] >= 0.95 for d in declarations), declarations
    for d, e in zip(declarations, episodes, strict=True):
        # Declared on step S: S moves applied, step S's moves not flown (no extra step).
        assert d["length"] == d["step"] == e["length"], (d, e)
        flown = [s["step"] for s in steps if s["episode"] == d["episode"]]
        assert flown == list(range(d["step"])), (d, flown)
    for log in logs:
        assert "Traceback" not in log.read_text()
