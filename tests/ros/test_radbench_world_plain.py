"""The field benchmark's world in the ROS graph, on its logic without spinning a node: the simulator's
core in that world, and the options that do not apply to it refused."""

from __future__ import annotations

import math

import pytest
import torch
from medc_sim.sim_core import SimConfig, SimCore

RADBENCH = dict(world="radbench", agents=3, walls=7, grid=20, max_steps=120, sensing="realistic", seed=3)


def _within(cells, target, radius: float) -> bool:
    return any(math.dist(c, target) <= radius for c in cells)


def test_the_simulator_plays_the_benchmarks_world_from_the_cores_state():
    core = SimCore(SimConfig(**RADBENCH))
    assert type(core.env).__name__ == "BenchWorld" and core.noise and core.sensing.name == "realistic"
    gen = torch.Generator().manual_seed(1)
    obstructed = 0
    while len(core.results) < 3:
        state = core.env.state(0)
        # What the node publishes is the core's own state.
        assert core.positions() == list(state.positions) and core.readings() == list(state.readings)
        assert torch.equal(core.walls(), state.walls) and core.target() == state.target
        assert all(float(v).is_integer() and v >= 0 for v in core.readings())  # Poisson counts
        obstructed += int(core.walls().any())
        before, episode = core.positions(), core.episode
        held = int(torch.randint(0, 3, (1,), generator=gen))
        actions = [int(a) for a in torch.randint(0, 8, (3,), generator=gen)]
        actions[held] = None
        result = core.advance(actions)
        if result.finished is None:
            assert core.positions()[held] == before[held]  # a held agent stays where it is
            assert core.step == state.step + 1
        else:
            done = result.finished
            assert done.episode == episode and core.episode == episode + 1 and core.step == 0
            assert done.success == (done.ended_by == "source") and (done.truncated or done.success)
            assert done.length <= RADBENCH["max_steps"]
    assert obstructed > 0


def test_an_episode_ended_by_the_driver_starts_the_next_one():
    core = SimCore(SimConfig(**RADBENCH))
    core.advance([0, 0, 0])
    first = core.env.state(0)
    target = core.target()
    result = core.end_by_declaration(target)
    assert result.success and result.error == 0.0 and result.length == first.step
    assert core.episode == 1 and core.step == 0 and core.results == [result]
    missed = core.end_by_declaration((target[0], (target[1] + 10) % 20))
    assert not missed.success and core.episode == 2


def test_a_step_that_does_not_end_the_episode_leaves_every_uav_outside_the_success_radius():
    """The agents rule out the cells near every UAV on a step that did not end the episode, so the
    simulator must end it exactly when a UAV comes within the radius."""
    core = SimCore(SimConfig(**{**RADBENCH, "walls": 0, "grid": 20, "seed": 8}))
    gen = torch.Generator().manual_seed(4)
    ended = []
    while len(ended) < 4:
        target = core.target()
        result = core.advance([int(a) for a in torch.randint(0, 8, (3,), generator=gen)])
        if result.finished is None:
            assert not _within(core.positions(), target, core.sensing.success_radius)
        else:
            ended.append(result.finished)
    assert all(r.success != r.truncated for r in ended)


@pytest.mark.parametrize("change, said", [
    ({"end_on": "declaration"}, "does not apply to the radbench world.*set end_on source"),
    ({"grid": 25}, "grids of 20 or 30 cells, got grid 25; set grid"),
    ({"walls": 8}, r"walls \(the most obstructions of a radbench episode\) must be 0..7, got 8"),
    ({"sensing": "paper-simple"}, "set sensing realistic"),
    ({"world": "moon"}, "world must be one of grid, radbench"),
])
def test_options_that_do_not_apply_to_the_benchmarks_world_are_refused(change, said):
    with pytest.raises(ValueError, match=said):
        SimCore(SimConfig(**{**RADBENCH, **change}))
