"""An agent node's memory builds the ``+information`` view exactly as the training core does."""

from __future__ import annotations

import torch
from medc_training.envs import make_batched
from medc_training.envs.tl_observation import parse_observation

VIEW = "ego6+estimate+posterior+information"


def test_the_ros_agent_memory_builds_the_training_observation():
    from medc_agents.team_memory import AgentMemory

    env = make_batched("target_localization", num_envs=1, seed=5, world="radbench", agents=3, walls=7,
                       grid=20, max_steps=120, sensing="realistic", observation=VIEW)
    env.reset()
    for _ in range(4):
        env.step(torch.randint(0, 8, (1, 3), generator=torch.Generator().manual_seed(5)))
    agent = AgentMemory(env.grid, env.sensing)
    agent.memory = env.memory  # the same history
    obs, _ = agent.observe(parse_observation(VIEW), env.positions, env.walls_f > 0.5, 1)
    assert torch.allclose(obs, env.memory.observe(env.positions, env.walls_f)[0, 1])
