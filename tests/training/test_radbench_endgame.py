"""medc_training.radbench.endgame: the team's own moves until the posterior's mode holds tau of the
mass, shortest-path moves towards it after; its episode lines pair with the team's. Played on a
set file generated here (not the frozen episodes)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
import torch
from medc_training.bundle import load_bundle
from medc_training.radbench.endgame import Endgame, main
from medc_training.radbench.oracle import move_costs, success_field
from medc_training.radbench.pairing import load_episodes, pair_table
from medc_training.radbench.play import BenchCore, play_set
from medc_training.radbench.sets import generate_file, load_sets, write_file

ROOT = Path(__file__).resolve().parents[2]
TEAM = ROOT / "docs/reproduction/learned-team/main-posterior-cnn9-ft/medc-s0/policy.safetensors"


@pytest.fixture(scope="module")
def sets_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("endgame") / "g20-a3.json"
    write_file(generate_file(20, 3, episodes=6, seed=4051, obstructions=[6], snrs=["low", "high"]), path)
    return path


def test_tau_one_is_the_team_alone_and_a_lower_tau_plans_the_end(sets_file, one_thread):
    bundle = load_bundle(TEAM)
    for s in load_sets(path=sets_file):
        never = Endgame(bundle, 1.0)
        assert play_set(s, never) == play_set(s, bundle) and never.planned == 0 and never.decisions > 0
        planner = Endgame(bundle, 0.9)
        assert all(r.success for r in play_set(s, planner))
        assert 0 < planner.planned < planner.decisions
    for tau in (0.0, 1.5, -1.0):
        with pytest.raises(ValueError, match="tau must be a number in"):
            Endgame(bundle, tau)


def test_the_endgame_walks_each_agent_a_shortest_path_to_the_mode(sets_file, monkeypatch, one_thread):
    """Where the mode holds tau, every agent's best allowed move is one of its fewest-move moves
    towards the mode's success region; elsewhere the scores are the network's."""
    bundle = load_bundle(TEAM)
    s = load_sets(path=sets_file)[0]
    core = BenchCore(s, [0, 1], observation=bundle.observation)
    obs, mask = core.reset()
    g, n = core.grid, core.num_agents
    free = (~core.walls[0]).flatten().nonzero().squeeze(1)
    mode = int(free[len(free) // 2])
    p = torch.full((2, g * g), 1.0 / (g * g))
    p[0] = 0.0
    p[0, mode] = 1.0  # episode 0 certain of a cell, episode 1 knows nothing
    monkeypatch.setattr(core.memory, "posterior", lambda: p)
    scores = Endgame(bundle, 0.9)(core)(obs.flatten(0, 1), mask.flatten(0, 1)).view(2, n, -1)
    target = torch.tensor([[mode // g, mode % g]])
    cost = move_costs(core.walls[:1], success_field(core.walls[:1], target, core.sensing), core.positions[:1])
    for i in range(n):
        best = int(scores[0, i].masked_fill(~mask[0, i], -math.inf).argmax())
        assert cost[0, i, best] == cost[0, i].min() < math.inf
    with torch.no_grad():
        own, _ = bundle.net(obs.flatten(0, 1))
    assert torch.equal(scores[1], own.view(2, n, -1)[1])


def test_the_standing_mass_is_the_posterior_within_the_success_radius():
    """Per free cell, the mass within the success radius (1.1 cells: the cell and its four
    neighbours), summed by hand; 0 on walls."""
    from medc_training.radbench.endgame import standing_mass
    from medc_training.radbench.physics import TEAM_SENSING

    g = 6
    walls = torch.zeros(1, g, g, dtype=torch.bool)
    walls[0, 0, :3] = True
    p = torch.rand(1, g * g, generator=torch.Generator().manual_seed(3))
    p = p / p.sum()
    mass = standing_mass(p, walls, TEAM_SENSING)[0]
    grid = p.view(g, g)
    for r in range(g):
        for c in range(g):
            want = sum(float(grid[r + dr, c + dc]) for dr, dc in ((0, 0), (1, 0), (-1, 0), (0, 1), (0, -1))
                       if 0 <= r + dr < g and 0 <= c + dc < g)
            assert mass[r, c].item() == pytest.approx(0.0 if walls[0, r, c] else want, abs=1e-6)


def test_the_region_trigger_plans_where_the_mode_does_and_where_the_mass_is_spread():
    """Where the mode holds tau (> 0.5) the region trigger's places are the mode's success region,
    so both give the same costs; where tau of the mass lies on two neighbouring cells only the
    region trigger plans, towards the cells from which both are within reach; a bad trigger is
    refused."""
    from medc_training.radbench.endgame import planned_costs
    from medc_training.radbench.physics import TEAM_SENSING

    g = 12
    walls = torch.zeros(2, g, g, dtype=torch.bool)
    walls[:, 4, 2:9] = True
    p = torch.full((2, g * g), 1e-5)
    p[0, 8 * g + 6] = 1.0
    p[1, 8 * g + 6] = p[1, 8 * g + 7] = 0.5
    p = p / p.sum(1, keepdim=True)
    positions = torch.tensor([[[0, 0], [11, 11], [2, 6]]] * 2)
    rows, mode_cost = planned_costs(p, walls, positions, TEAM_SENSING, 0.9, "mode")
    assert rows.tolist() == [0]
    rows, region_cost = planned_costs(p, walls, positions, TEAM_SENSING, 0.9, "region")
    assert rows.tolist() == [0, 1] and torch.equal(region_cost[0], mode_cost[0])
    both = torch.tensor([[8, 6], [8, 7]])  # the only cells with both within 1.1 cells
    field = success_field(walls[1:].expand(2, g, g), both, TEAM_SENSING)
    goal = (field == 0).all(0)
    assert goal.sum() == 2 and goal[8, 6] and goal[8, 7]
    from medc_training.envs.grid import bfs_distance

    want = move_costs(walls[1:], bfs_distance(~walls[1:], goal.unsqueeze(0)), positions[1:])
    assert torch.equal(region_cost[1], want[0])
    with pytest.raises(ValueError, match="trigger must be one of mode, region"):
        Endgame(load_bundle(TEAM), 0.9, "cell")


def test_its_lines_pair_with_the_teams_lines(sets_file, tmp_path, capsys, one_thread):
    from medc_training.cli.radbench import main as radbench

    out, team = tmp_path / "endgame.jsonl", tmp_path / "team.jsonl"
    argv = [str(TEAM), "--tau", "0.9", "--sets-file", str(sets_file), "--obstructions", "6",
            "--episodes", "3", "--out", str(out)]
    assert main(argv) == 0 and "medc-s0+endgame0.9: 6 episodes" in capsys.readouterr().out
    assert main(argv) == 2 and "overwrite" in capsys.readouterr().err  # never replaced unasked
    assert radbench([str(TEAM), "--sets-file", str(sets_file), "--grid", "20", "--agents", "3",
                     "--obstructions", "6", "--episodes", "3", "--quiet", "--out", str(team)]) == 0
    table = pair_table(load_episodes([team, out]), "medc-s0")
    assert table["episodes"] == 6 and "paired" in table["groups"]["obs5-7"]["medc-s0+endgame0.9"]


def test_under_a_background_prior_tau_one_plays_as_the_team_under_it(sets_file, tmp_path, capsys, one_thread):
    from medc_training.cli.radbench import main as radbench

    out, team = tmp_path / "endgame.jsonl", tmp_path / "team.jsonl"
    common = ["--sets-file", str(sets_file), "--obstructions", "6", "--episodes", "3",
              "--prior-background", "10,50,16"]
    assert main([str(TEAM), "--tau", "1", *common, "--out", str(out)]) == 0
    assert radbench([str(TEAM), *common, "--grid", "20", "--agents", "3", "--quiet", "--out", str(team)]) == 0
    capsys.readouterr()
    played = load_episodes([team, out])
    alone, planned = played["medc-s0"], played["medc-s0+endgame1"]
    assert alone.keys() == planned.keys() and len(alone) == 6
    assert all((alone[k].length, alone[k].track_rmse_m) == (planned[k].length, planned[k].track_rmse_m)
               for k in alone)
    assert main([str(TEAM), "--tau", "1", *common[:-1], "5,100", "--out", str(out), "--overwrite"]) == 2
    assert "LOW,HIGH,LEVELS" in capsys.readouterr().err


def test_medc_radbench_endgame_plays_as_the_endgame_module_and_its_lines_say_so(sets_file, tmp_path, capsys,
                                                                                 one_thread):
    """``medc-radbench --endgame TAU``: every bundle plays with the endgame (the same episodes as
    the module's), a controller beside it is unaffected, the lines carry the tau so a pairing names
    the planned team apart, and a sampled team or a tau outside (0, 1] is refused."""
    from medc_training.cli.radbench import main as radbench

    out, module = tmp_path / "cli.jsonl", tmp_path / "module.jsonl"
    common = ["--sets-file", str(sets_file), "--obstructions", "6", "--episodes", "3",
              "--prior-background", "10,50,16"]
    assert radbench([str(TEAM), "greedy", *common, "--agents", "3", "--endgame", "0.9", "--quiet",
                     "--out", str(out)]) == 0
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert summary["endgame"] == 0.9
    assert main([str(TEAM), "--tau", "0.9", *common, "--out", str(module)]) == 0
    capsys.readouterr()
    cli = load_episodes([out])
    assert set(cli) == {"medc-s0+endgame0.9", "greedy"}
    mine = load_episodes([module])["medc-s0+endgame0.9"]
    assert cli["medc-s0+endgame0.9"] == mine and len(mine) == 6
    for bad in (["--temperature", "0.5"], ["--endgame", "0"], ["--endgame", "1.5"]):
        argv = [str(TEAM), *common, "--agents", "3", "--quiet", *bad]
        if "--temperature" in bad:
            argv += ["--endgame", "0.9"]
        assert radbench(argv) == 2
        assert "endgame" in capsys.readouterr().err


def test_the_node_decision_cost_plans_with_the_endgame(one_thread, capsys):
    """With an endgame, an agent node's decision cost includes its planning: at a tau every
    posterior holds, each timed node decision plans; without one none does; ``medc-radbench
    --cost`` measures under the team's model and endgame it is given, and says so."""
    from medc_training.cli.radbench import main as radbench
    from medc_training.radbench.cost import decision_cost
    from medc_training.radbench.physics import team_sensing

    (s,) = load_sets(grid=20, agents=3, obstructions=[3], snrs=["medium"])
    bundle = load_bundle(TEAM)
    planned = decision_cost(s, bundle, batch=2, steps=1, node_steps=3, sensing=team_sensing("10,50,16"),
                            endgame=1e-9)
    assert planned["endgame_decisions"] == 3 and planned["endgame_ms_p50"] > 0
    alone = decision_cost(s, bundle, batch=2, steps=1, node_steps=3)
    assert "endgame_decisions" not in alone and alone["node_ms_p50"] > 0
    never = decision_cost(s, bundle, batch=2, steps=1, node_steps=3, endgame=1.0)
    assert never["endgame_decisions"] == 0 and "endgame_ms_p50" not in never
    with pytest.raises(ValueError, match="tau must be a number in"):
        decision_cost(s, bundle, batch=2, steps=1, node_steps=3, endgame=0.0)
    assert radbench(["--cost", str(TEAM), "--agents", "3", "--batch", "2", "--prior-background", "10,50,16",
                     "--endgame", "0.9"]) == 0
    printed = capsys.readouterr().out
    assert "background prior 10-50 counts/s at 16 levels" in printed and "endgame at tau 0.9" in printed
    out = json.loads(printed.strip().splitlines()[-1])
    assert out["background_prior"] == [10, 50, 16] and out["endgame"] == 0.9
    assert "endgame_decisions" in out["cost"][str(TEAM)]
