"""The team's source estimate on the graph (docs/ros-reference.md, "The team's source estimate"): the estimate
topic converges to the source, the team declares it, and the simulator ends episodes on the
declaration (``end_on``), with the shipped team (models/team, paper-simple, 13x13)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from ros_helpers import spin_until

TEAM = Path(__file__).resolve().parents[2] / "models" / "team" / "A3W2.safetensors"
EPISODES = 6


def _monitor(sim):
    """A node that records, per episode, the team's estimates and declarations and the true source
    (read from the in-process simulator while it plays the episode of a status heard)."""
    import rclpy
    from geometry_msgs.msg import PoseWithCovarianceStamped
    from medc_common import contract
    from medc_interfaces.msg import EpisodeStatus, SourceDeclaration
    from nav_msgs.msg import OccupancyGrid

    node = rclpy.create_node("estimate_monitor")
    seen = {"targets": {}, "stamps": {}, "estimates": [], "declarations": [], "heat_maps": []}

    def on_status(msg):
        if not msg.done:
            key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
            episode = int(msg.episode)
            seen["stamps"][key] = episode
            # The simulator re-sends a step the team is slow to answer (every resend_s): a copy
            # heard after its episode ended (the team declared meanwhile) must not give that
            # episode the next one's source. Its first step is heard while it is played.
            if episode == sim.core.episode:
                seen["targets"].setdefault(episode, sim.geometry.cell_to_xy(*sim.core.target()))

    ns = "/medc"
    node.create_subscription(EpisodeStatus, contract.status_topic(ns), on_status, contract.RELIABLE_QOS)
    node.create_subscription(PoseWithCovarianceStamped, contract.estimate_topic(ns),
                             seen["estimates"].append, contract.ESTIMATE_QOS)
    node.create_subscription(SourceDeclaration, contract.declaration_topic(ns), seen["declarations"].append,
                             contract.RELIABLE_QOS)
    node.create_subscription(OccupancyGrid, contract.posterior_topic(ns), seen["heat_maps"].append,
                             contract.LATCHED_QOS)
    return node, seen


@pytest.mark.timing
@pytest.mark.ros
@pytest.mark.parametrize("end_on", ["declaration", "either"])
def test_estimate_converges_and_the_declaration_ends_episodes(graph, end_on):
    executor, sim, agents = graph(TEAM, EPISODES, end_on=end_on, seed=3)
    monitor, seen = _monitor(sim)
    executor.add_node(monitor)
    # Every agent may publish; agent_0, the lowest-numbered live one, does (EstimateRole).
    assert [a.estimate.enabled for a in agents] == [True, True, True]
    assert [a.estimate.publishing for a in agents] == [True, False, False]
    assert agents[0].observer.rule_out == (end_on != "declaration")
    assert spin_until(executor, lambda: sim.finished, 120), f"only {len(sim.core.results)} episodes"
    results = sim.core.results
    by_decl = [r for r in results if r.ended_by == "declaration"]
    # The declaration that ended the last episode may still wait in the monitor's queue (under
    # 'either' some episodes end on the source, so no count of declarations is the one to wait for).
    declared_episodes = lambda: {int(d.episode) for d in seen["declarations"]}  # noqa: E731
    spin_until(executor, lambda: {r.episode for r in by_decl} <= declared_episodes(), 30)
    if end_on == "declaration":
        assert len(by_decl) == EPISODES  # a finding never ends an episode under this rule
    assert len(by_decl) >= EPISODES - 2, [r.ended_by for r in results]
    assert all(r.success and r.error == 0.0 for r in by_decl), [(r.error, r.length) for r in by_decl]

    # Every declaration names its episode, the step it was decided on and the source's cell.
    declared = {int(d.episode): d for d in seen["declarations"]}
    for r in by_decl:
        d = declared[r.episode]
        assert d.step == r.length and d.agent_id == "agent_0" and d.header.frame_id == "map"
        tx, ty = seen["targets"][r.episode]
        assert math.hypot(d.position.x - tx, d.position.y - ty) < 1e-6
        assert d.mass >= d.threshold == 0.95 and d.radius_cells == 0.0

    # The estimate topic: one per decided step, in the map frame; per episode it ends on the source
    # with a spread no wider than a cell, and it is closer there than at the episode's first step.
    per_episode: dict[int, list] = {}
    for est in seen["estimates"]:
        episode = seen["stamps"][(est.header.stamp.sec, est.header.stamp.nanosec)]
        per_episode.setdefault(episode, []).append(est)
    assert set(per_episode) == {r.episode for r in results}
    for r in by_decl:
        tx, ty = seen["targets"][r.episode]
        ests = per_episode[r.episode]
        last = ests[-1]
        assert last.header.frame_id == "map"
        err_last = math.hypot(last.pose.pose.position.x - tx, last.pose.pose.position.y - ty)
        spread = math.sqrt(last.pose.covariance[0] + last.pose.covariance[7])
        assert err_last < 0.5 and spread < 1.0, (err_last, spread)
        first = ests[0]
        err_first = math.hypot(first.pose.pose.position.x - tx, first.pose.pose.position.y - ty)
        assert err_last <= err_first + 1e-9
    # The heat map lies on the walls map's grid, 100 at the most probable cell.
    assert seen["heat_maps"], "no posterior heat map"
    heat = seen["heat_maps"][-1]
    assert (heat.info.width, heat.info.height) == (13, 13) and max(heat.data) == 100
    assert sim.dropped == 0 and all(a.dropped == 0 for a in agents)
    assert [a.estimate.publishing for a in agents] == [True, False, False]  # nobody was lost


@pytest.mark.timing
@pytest.mark.ros
def test_source_rule_is_today_s_and_ignores_declarations(graph):
    """end_on: source (the default): episodes end as in training, whatever the team declares."""
    executor, sim, agents = graph(TEAM, 3, seed=3)
    assert spin_until(executor, lambda: sim.finished, 120)
    assert {r.ended_by for r in sim.core.results} <= {"source", "max_steps"}
    assert agents[0].estimate.declarations >= 1  # the team still says it


@pytest.mark.parametrize("yaw", [0.0, math.pi / 2, 0.7])
def test_estimate_in_map_follows_the_grid_geometry(yaw):
    """A posterior mean on a cell centre lands on that cell's centre in the map frame (origin, yaw,
    resolution); a spread along a grid column (rows) becomes a spread along the grid frame's y."""
    from medc_agents.estimate import estimate_in_map
    from medc_common.contract import GridGeometry

    geo = GridGeometry(9, 9, 2.0, 250.0, -80.0, yaw)
    (x, y), cov = estimate_in_map((3.0, 5.0), [[4.0, 0.0], [0.0, 0.0]], geo)
    assert (x, y) == pytest.approx(geo.cell_to_xy(3, 5))
    # Variance 4 cells² along rows (+1/12 within a cell), 1/12 along columns, times r² = 4 m².
    along_j, along_i = (4.0 + 1 / 12) * 4.0, (1 / 12) * 4.0
    c, s = math.cos(yaw), math.sin(yaw)
    assert cov[0][0] == pytest.approx(c * c * along_i + s * s * along_j)
    assert cov[1][1] == pytest.approx(s * s * along_i + c * c * along_j)
    assert cov[0][1] == pytest.approx(cov[1][0]) == pytest.approx(c * s * (along_i - along_j))


def test_heat_map_rows_follow_the_occupancy_grid():
    """data[j * width + i] holds environment row H - 1 - j: the first message row is the southern."""
    import torch
    from medc_agents.estimate import heat_map_data

    p = torch.zeros(4 * 4)
    p[0 * 4 + 1] = 0.8  # environment row 0 (north), col 1
    p[3 * 4 + 2] = 0.2  # row 3 (south), col 2
    data = heat_map_data(p, 4)
    assert data[3 * 4 + 1] == 100 and data[0 * 4 + 2] == 25 and sum(data) == 125


def test_episode_end_rules_and_judging_a_declaration():
    from medc_sim.episode_end import check_end_rule, declared_cell, judge

    rules = ["source", "declaration", "either"]
    assert [check_end_rule(r) for r in rules] == rules
    with pytest.raises(ValueError, match="end_on must be one of"):
        check_end_rule("first")
    assert declared_cell(2, 0, 5) == (4, 2)  # i = col, j = 0 is the southern row
    with pytest.raises(ValueError, match="outside"):
        declared_cell(5, 0, 5)
    assert judge((4, 2), (4, 2), 0.0) == (0.0, True)
    assert judge((4, 2), (3, 2), 0.0) == (1.0, False)
    assert judge((4, 2), (3, 2), 1.1)[1] and not judge((4, 2), (3, 3), 1.1)[1]


@pytest.mark.timing
@pytest.mark.ros
def test_medc_launch_ends_episodes_on_the_declaration_with_agent_processes(tmp_path):
    """The deployment shape: the simulator and one medc-agent process per UAV, `end_on: declaration`
    in the launch config (the launcher gives the agents source_ends_episode false): every episode
    ends on the team's declaration of the right cell, before a UAV could have reached it."""
    import json
    import subprocess
    import sys

    config = tmp_path / "launch.yaml"
    config.write_text(json.dumps({"policy": str(TEAM), "end_on": "declaration", "seed": 3}))  # JSON is YAML
    launcher = Path(sys.executable).parent / "medc-launch"
    out = subprocess.run([str(launcher), "--config", str(config), "--episodes", "5", "--timeout", "150"],
                         capture_output=True, text=True, timeout=200)
    assert out.returncode == 0, out.stderr[-3000:]
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result["episodes"] == 5 and result["success_rate"] == 1.0, result
    assert result["end_on"] == "declaration" and result["mean_length"] < 4, result
