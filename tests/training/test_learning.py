"""A short PPO run learns: episode length falls on a small environment whose answer is in the obs.

The environment here is a small batched env written to the same contract as
medc_training.envs (obs [B,N,C,H,W], masks, team reward, termination/truncation, final_obs):
each episode a goal marker sits at the left or right edge of channel 0 and the team finishes
as soon as every agent moves towards it (E or W); otherwise it is truncated after 6 steps.
Random play needs ~4 steps per episode; a policy that reads its observation needs 1. This checks
the PPO core, masks included, in seconds; the last test shows learning on target localization
itself with the default observation and learner.
"""

import types

import torch
from medc_training.config import TrainConfig
from medc_training.ppo import Trainer

EAST, WEST = 2, 6


class GoalSideEnv:
    def __init__(self, num_envs: int, num_agents: int = 2, seed: int = 0, max_steps: int = 6) -> None:
        self.num_envs, self.num_agents, self.num_actions = num_envs, num_agents, 8
        self.obs_shape = (5, 4, 4)
        self.device = torch.device("cpu")
        self.attributes = {"agents": num_agents}
        self.max_steps = max_steps
        self.gen = torch.Generator().manual_seed(seed)
        self.side = torch.zeros(num_envs, dtype=torch.long)
        self.t = torch.zeros(num_envs, dtype=torch.long)

    def _mask(self) -> torch.Tensor:
        mask = torch.ones(self.num_envs, self.num_agents, 8, dtype=torch.bool)
        mask[..., 0] = False  # N is never allowed: the learner must honour masks
        return mask

    def _obs(self) -> torch.Tensor:
        obs = torch.zeros(self.num_envs, self.num_agents, *self.obs_shape)
        obs[torch.arange(self.num_envs), :, 0, 1, self.side * 3] = 1.0
        return obs

    def _new(self, rows: torch.Tensor) -> None:
        self.side[rows] = torch.randint(0, 2, (len(rows),), generator=self.gen)
        self.t[rows] = 0

    def reset(self, seed=None):
        if seed is not None:
            self.gen.manual_seed(seed)
        self._new(torch.arange(self.num_envs))
        return self._obs(), self._mask()

    def step(self, actions):
        assert not (actions == 0).any(), "a masked action was sampled"
        want = torch.where(self.side == 0, WEST, EAST).unsqueeze(1)
        success = (actions == want).all(1)
        self.t += 1
        truncated = (self.t >= self.max_steps) & ~success
        done = success | truncated
        length = self.t.clone()
        final = self._obs()
        self._new(done.nonzero(as_tuple=True)[0])
        return types.SimpleNamespace(obs=self._obs(), mask=self._mask(), reward=success.float() * 10,
                                     terminated=success, truncated=truncated, final_obs=final,
                                     episode_length=length, success=success)


def test_ppo_episode_length_falls():
    cfg = TrainConfig(agents=2, num_envs=16, horizon=256, epochs=4, minibatches=4, arch="mlp", eval_steps=256,
                      eval_envs=16, total_steps=10**9, seed=0, lr=1e-3)
    trainer = Trainer(cfg, env=GoalSideEnv(16, seed=1), eval_env=GoalSideEnv(16, seed=2))
    before = trainer.evaluate()["episode_length"]
    first = None
    for update in range(20):
        trainer.train_update()
        if update == 1:
            first = trainer.take_train_stats()["episode_length"]
    last = trainer.take_train_stats()["episode_length"]
    after = trainer.evaluate()
    print(f"eval before {before:.2f}, train first {first:.2f}, last {last:.2f}, eval after {after}")
    assert first > 3.0, f"random play should need several steps, got {first}"
    assert last < 0.6 * first
    assert after["episode_length"] < 0.6 * before and after["success_rate"] > 0.9


def test_target_localization_learns_with_the_default_observation_and_learner():
    """MDRL-sparse on a small target-localization env (A1W0, 7x7, 20-step episodes), the default
    observation (agent-centred window + the team's source estimate) and the CPU scale's learner:
    the greedy episode length falls to well under 60% of the untrained policy's in ~40k steps."""
    from medc_training.config import scaled_config

    cfg = scaled_config("cpu", agents=1, walls=0, grid=7, max_steps=20, total_steps=10**9, seed=0,
                        eval_steps=640, eval_envs=32, torch_threads=1)
    trainer = Trainer(cfg)
    before = trainer.evaluate()
    for _ in range(40):
        trainer.train_update()
    after = trainer.evaluate()
    print(f"greedy eval before {before}, after {after}")
    assert after["episode_length"] <= 0.6 * before["episode_length"]
    assert after["success_rate"] > 0.5
