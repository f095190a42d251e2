"""The one PPO core: centralized learning, decentralized execution, with MEDC/IL/RS hooks.

Read top to bottom: :meth:`Trainer.collect` fills a rollout of ``horizon`` training steps
(each agent acts on its own observation with the one shared actor-critic; the team reward
is every agent's reward), :meth:`Trainer.update` runs ``epochs`` passes of clipped PPO over
it, :meth:`Trainer.evaluate` plays ``eval_episodes`` fixed episodes to their ends
(:func:`medc_training.evaluate.play_episodes`; or, for a run with ``eval_episodes`` 0, the legacy
window the research harness keeps). The methods differ only in:

- ``sparse``: nothing extra (MDRL-sparse).
- ``rs``: the environment is built with ``reward_shaping=True`` (BFS-shaped reward).
- ``medc``: in expert-guided episodes (probability R_E per episode) the action comes from
  :func:`medc_training.medc.follow_expert`; the stored log-prob is the agent's own.
- ``il``: in expert-guided episodes the agents take the expert's best valid action, and those
  samples are trained by behavioural cloning (no reward, no PPO loss).
- ``frl``: several Trainers whose parameters are averaged (see :mod:`medc_training.frl`).
"""

from __future__ import annotations

import random
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from .buffer import RolloutBuffer
from .config import TrainConfig
from .evaluate import net_policy, play_episodes, registered_evaluator, summarize_episodes
from .experts import Expert
from .losses import approx_kl, bc_loss, masked_mean, ppo_policy_loss, value_loss
from .medc import expert_episode_draw, expert_scores_for, follow_expert, roulette_wheel
from .nets import make_actor_critic, masked_logits
from .qos import expert_weights_from_attributes, normalised_weights

#: Evaluation episodes are drawn from ``seed + EVAL_SEED_OFFSET``: a stream far from the training
#: environments' seeds, and the same for every method and every user of an FRL group.
EVAL_SEED_OFFSET = 1_000_003


def seed_everything(seed: int) -> None:
    """Seed Python, numpy and torch (CPU and CUDA) global generators."""
    random.seed(seed)
    np.random.seed(seed % (2**32))
    torch.manual_seed(seed)


def make_env_for(cfg: TrainConfig, num_envs: int, seed: int, reward_shaping: bool, **extra):
    """The batched environment a config describes (:meth:`TrainConfig.make_options`); ``extra``:
    further core options over the config's (e.g. ``posterior=True``, which the classical controllers
    need and which changes no episode)."""
    from .envs import make_batched

    return make_batched(cfg.env, num_envs=num_envs, device=cfg.device, seed=seed,
                        **{**cfg.make_options(reward_shaping), **extra})


@dataclass
class EpisodeStats:
    """Finished-episode statistics accumulated between two log points."""

    lengths: list = field(default_factory=list)
    successes: list = field(default_factory=list)
    returns: list = field(default_factory=list)

    def add(self, lengths: torch.Tensor, successes: torch.Tensor, returns: torch.Tensor) -> None:
        self.lengths.extend(lengths.tolist())
        self.successes.extend(successes.float().tolist())
        self.returns.extend(returns.tolist())

    def summary(self, default_length: float) -> dict:
        return summarize_episodes(self.lengths, self.successes, self.returns, default_length)


def expert_slices(experts: Sequence[Expert], weights, cfg: TrainConfig) -> torch.Tensor | None:
    """R_S as float32 [num experts]: ``weights`` normalised, or (None) the QoS rule's from the
    experts' environment attributes; None without experts or weights."""
    if weights is None:
        if not experts:
            return None
        weights = expert_weights_from_attributes([e.attributes for e in experts], cfg.env_attributes())
    else:
        if isinstance(weights, torch.Tensor):
            weights = weights.detach().cpu().tolist()
        weights = normalised_weights(weights, len(experts))
        if not weights:
            return None
    return torch.tensor(weights, dtype=torch.float64).float()


def minibatch_loss(net, mb: dict, cfg: TrainConfig, device: torch.device) -> tuple:
    """(loss, (policy, value, entropy, BC losses), log ratios, RL-sample mask) of one minibatch:
    clipped PPO with value and entropy terms on the RL samples, behavioural cloning on IL's."""
    logits, new_value = net(mb["obs"])
    logits = masked_logits(logits, mb["masks"])
    logp_all = torch.log_softmax(logits, dim=-1)
    new_logprob = logp_all.gather(-1, mb["actions"].unsqueeze(-1)).squeeze(-1)
    entropy = -(logp_all.exp() * logp_all).sum(-1)
    rl = ~mb["bc"]
    adv = mb["advantages"]
    if cfg.norm_adv and rl.sum() > 1:
        sel = adv[rl]
        adv = (adv - sel.mean()) / (sel.std() + 1e-8)
    pg, log_ratio = ppo_policy_loss(new_logprob, mb["logprobs"], adv, cfg.clip)
    pg_loss = masked_mean(pg, rl)
    v_loss = masked_mean(value_loss(new_value, mb["returns"]), rl)
    ent = masked_mean(entropy, rl)
    loss = pg_loss - cfg.ent_coef * ent + cfg.vf_coef * v_loss
    b_loss = torch.zeros((), device=device)
    if mb["bc"].any():
        b_loss = masked_mean(bc_loss(logits, mb["actions"]), mb["bc"])
        loss = loss + cfg.bc_coef * b_loss
    return loss, (pg_loss, v_loss, ent, b_loss), log_ratio, rl


@torch.no_grad()
def explained_variance(buffer: RolloutBuffer) -> float:
    """1 - Var(returns - values) / Var(returns) over the rollout's RL samples (CleanRL's
    ``losses/explained_variance``; NaN when the returns do not vary)."""
    rl = ~buffer.bc
    y_true, y_pred = buffer.returns[rl].double(), buffer.values[rl].double()
    if y_true.numel() < 2:
        return float("nan")
    var_y = y_true.var(unbiased=False)
    if float(var_y) == 0.0:
        return float("nan")
    return float(1.0 - (y_true - y_pred).var(unbiased=False) / var_y)


class Trainer:
    """One learner: environment, shared actor-critic, optimiser, experts, counters.

    ``expert_weights`` are the experts' roulette-wheel slices R_S, one per expert (finite, >= 0,
    not all 0; normalised here), e.g. the R_S of the registry's allocation. None: computed from
    the experts' environment attributes by the contract's QoS rule (:mod:`medc_training.qos`).
    """

    def __init__(self, cfg: TrainConfig, experts: Sequence[Expert] = (),
                 expert_weights: Sequence[float] | None = None, env=None, eval_env=None) -> None:
        cfg.validate()
        self.cfg = cfg
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        seed_everything(cfg.seed)
        self.device = torch.device(cfg.device)
        if self.device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError("device 'cuda' requested but torch.cuda.is_available() is False")
        self.env = env if env is not None else make_env_for(cfg, cfg.num_envs, cfg.seed, cfg.method == "rs")
        # Evaluation restarts from this seed every time (FRL sets one seed for all its users).
        self.eval_seed = cfg.seed + EVAL_SEED_OFFSET
        self.eval_env = eval_env if eval_env is not None else make_env_for(
            cfg, cfg.eval_envs, self.eval_seed, False)
        self.B, self.N, self.A = self.env.num_envs, self.env.num_agents, self.env.num_actions
        self.obs_shape = tuple(self.env.obs_shape)
        self.net = make_actor_critic(cfg.arch, self.obs_shape, self.A, device=self.device)
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=cfg.lr, eps=1e-5)
        # A dedicated generator for MEDC draws and minibatch order keeps runs reproducible
        # regardless of how many random numbers the environment or the experts consume.
        self.generator = torch.Generator().manual_seed(cfg.seed + 7)
        self.experts = list(experts)
        if cfg.method in ("medc", "il") and not self.experts:
            raise ValueError(f"method {cfg.method!r} needs at least one expert (--expert)")
        for expert in self.experts:
            expert.check_compatible(self.obs_shape, self.A,
                                    observation=getattr(self.env, "observation_name", None))
            expert.bind(self.env)
        self.expert_weights = expert_slices(self.experts, expert_weights, cfg)
        self.buffer = RolloutBuffer(cfg.rollout_len, self.B, self.N, self.obs_shape, self.A, self.device)
        self.global_step = 0
        self.updates = 0
        self.stats = EpisodeStats()
        self.follow_counts = torch.zeros(3, dtype=torch.long)  # [followed, guided agent-steps, took top]
        self.expert_steps = 0
        self._last_step_mark = 0
        self._ep_return = torch.zeros(self.B, device=self.device)
        self.reset_envs(cfg.seed)

    # ----------------------------------------------------------------- rollout -----
    def reset_envs(self, seed: int | None) -> None:
        """Start fresh episodes in every training environment (also after a resume)."""
        self.obs, self.mask = self.env.reset(seed=seed)
        self._ep_return.zero_()
        self.expert_episode = self._draw_expert_episodes(self.B)

    def _draw_expert_episodes(self, n: int) -> torch.Tensor:
        if self.cfg.method not in ("medc", "il"):
            return torch.zeros(n, dtype=torch.bool, device=self.device)
        return expert_episode_draw(n, self.cfg.expert_rate, self.generator).to(self.device)

    def _policy(self, obs_flat: torch.Tensor, mask_flat: torch.Tensor):
        logits, value = self.net(obs_flat)
        return torch.distributions.Categorical(logits=masked_logits(logits, mask_flat)), value

    def _expert_actions(self, obs_flat, mask_flat, probs, actions, bc):
        """Apply MEDC or IL to the rows of expert-guided episodes (in place)."""
        rows = self.expert_episode.repeat_interleave(self.N).nonzero(as_tuple=True)[0]
        if rows.numel() == 0:
            return
        choice = roulette_wheel(self.expert_weights, rows.numel(), self.generator)
        scores = expert_scores_for(self.experts, choice, obs_flat, mask_flat, rows)
        if self.cfg.method == "medc":
            chosen, followed = follow_expert(probs[rows], scores, mask_flat[rows], self.cfg.q_threshold)
        else:  # IL: clone the expert blindly (no Q filter), whatever its own policy says
            chosen, followed = follow_expert(torch.ones_like(probs[rows]), scores, mask_flat[rows], 0.0)
            bc[rows[followed]] = True
        actions[rows[followed]] = chosen[followed]
        # The paper's "expert involvement": how often the move taken is the expert's own first
        # choice. A full-ranking expert always has *some* eligible move, so "followed" alone
        # stays at 1; the top-choice rate falls as the policy sharpens and Q filters the best.
        valid_scores = scores.masked_fill(~mask_flat[rows], float("-inf"))
        top = valid_scores.argmax(-1)
        has_top = torch.isfinite(valid_scores).any(-1)
        took_top = followed & has_top & (chosen == top)
        self.follow_counts += torch.tensor([int(followed.sum()), rows.numel(), int(took_top.sum())])

    @torch.no_grad()
    def collect(self) -> None:
        """Fill the rollout buffer with ``rollout_len`` batched steps (Algorithms 1-2)."""
        buf, B, N = self.buffer, self.B, self.N
        trunc_values = torch.zeros_like(buf.values)
        for t in range(buf.steps):
            obs_flat = self.obs.reshape(B * N, *self.obs_shape)
            mask_flat = self.mask.reshape(B * N, self.A)
            dist, value = self._policy(obs_flat, mask_flat)
            actions = dist.sample()
            bc = torch.zeros(B * N, dtype=torch.bool, device=self.device)
            if self.experts and self.cfg.method in ("medc", "il"):
                self._expert_actions(obs_flat, mask_flat, dist.probs, actions, bc)
                self.expert_steps += int(self.expert_episode.sum())
            buf.obs[t] = self.obs
            buf.masks[t] = self.mask
            buf.actions[t] = actions.view(B, N)
            buf.logprobs[t] = dist.log_prob(actions).view(B, N)
            buf.values[t] = value.view(B, N)
            buf.bc[t] = bc.view(B, N)

            out = self.env.step(actions.view(B, N))
            reward = out.reward.to(self.device).float()
            # IL's expert samples are stored with their reward but masked out of the PPO and
            # value losses in update(): they teach by cloning only.
            buf.rewards[t] = reward
            buf.terminated[t] = out.terminated
            buf.truncated[t] = out.truncated
            self._ep_return += reward
            done = out.terminated | out.truncated
            if out.truncated.any():
                idx = out.truncated.nonzero(as_tuple=True)[0]
                final = out.final_obs[idx].reshape(-1, *self.obs_shape)
                trunc_values[t, idx] = self.net(final)[1].view(-1, N)
            if done.any():
                idx = done.nonzero(as_tuple=True)[0]
                # Training statistics describe the agents' own (unguided) episodes only, so
                # that MEDC/IL curves are not flattered by the experts' steps.
                own = idx[~self.expert_episode[idx]]
                self.stats.add(out.episode_length[own].cpu(), out.success[own].cpu(),
                               self._ep_return[own].cpu())
                self._ep_return[idx] = 0.0
                self.expert_episode[idx] = self._draw_expert_episodes(idx.numel())
            self.obs, self.mask = out.obs, out.mask
            self.global_step += B

        last_value = self.net(self.obs.reshape(B * N, *self.obs_shape))[1].view(B, N)
        buf.next_values[:-1] = buf.values[1:]
        buf.next_values[-1] = last_value
        buf.next_values = torch.where(buf.truncated.unsqueeze(-1), trunc_values, buf.next_values)
        buf.compute_advantages(self.cfg.gamma, self.cfg.gae_lambda)

    # ------------------------------------------------------------------ update -----
    def update(self) -> dict:
        """``epochs`` passes of clipped PPO (and BC on IL samples) over the rollout, at the learning
        rate of the schedule (``lr_anneal_steps``) for the steps trained so far."""
        cfg = self.cfg
        if cfg.lr_anneal_steps > 0:
            frac = max(0.0, 1.0 - self.global_step / cfg.lr_anneal_steps)
            for group in self.optimizer.param_groups:
                group["lr"] = cfg.lr * frac
        sums: dict[str, float] = {}
        count = 0
        for _ in range(cfg.epochs):
            for mb in self.buffer.minibatches(cfg.minibatches, self.generator):
                loss, losses, log_ratio, rl = minibatch_loss(self.net, mb, cfg, self.device)
                pg_loss, v_loss, ent, b_loss = losses
                self.optimizer.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), cfg.max_grad_norm)
                self.optimizer.step()
                with torch.no_grad():
                    kl = approx_kl(log_ratio[rl]) if rl.any() else torch.zeros(())
                    clipfrac = ((log_ratio[rl].exp() - 1).abs() > cfg.clip).float().mean() if rl.any() else kl
                for k, v in (("policy_loss", pg_loss), ("value_loss", v_loss), ("entropy", ent),
                             ("approx_kl", kl), ("clipfrac", clipfrac), ("bc_loss", b_loss)):
                    sums[k] = sums.get(k, 0.0) + float(v.detach())
                count += 1
        self.updates += 1
        out = {k: v / max(count, 1) for k, v in sums.items()}
        out["explained_variance"] = self.explained_variance()
        out["learning_rate"] = float(self.optimizer.param_groups[0]["lr"])
        return out

    def explained_variance(self) -> float:
        """The rollout's explained variance (:func:`explained_variance`)."""
        return explained_variance(self.buffer)

    # -------------------------------------------------------------- evaluation -----
    @torch.no_grad()
    def evaluate(self, seed: int | None = None) -> dict:
        """Test play (greedy, or sampled without ``cfg.eval_greedy``): the summary of
        ``cfg.eval_episodes`` fixed episodes from the evaluation seed, the same every time
        (:func:`medc_training.evaluate.play_episodes`); ``eval_episodes`` 0: the harness's window."""
        env, cfg = self.eval_env, self.cfg
        seed = self.eval_seed if seed is None else seed
        # Sampled evaluation draws from its own generator (Gumbel-max on the device), restarted from
        # the evaluation seed, so it neither consumes nor depends on the training random streams.
        policy = net_policy(self.net)
        if cfg.eval_episodes:
            return play_episodes(env, policy, episodes=cfg.eval_episodes, greedy=cfg.eval_greedy, seed=seed,
                                 sampling="gumbel").summary()
        return registered_evaluator("window")(env, policy, cfg, seed)

    # -------------------------------------------------------------- the loop API ---
    def train_update(self) -> dict:
        """Collect one rollout and update on it; returns the update's losses."""
        self.collect()
        return self.update()

    @property
    def focal(self) -> Trainer:
        """The learner whose policy is evaluated and shipped (itself; FRL picks one user)."""
        return self

    def side_names(self) -> list[str]:
        """Other learners whose evaluation curves the run loop records: none for one Trainer."""
        return []

    def side_evaluate(self) -> dict[str, dict]:
        """Evaluation of each of :meth:`side_names` (none for one Trainer)."""
        return {}

    def state_dict(self) -> dict:
        """Everything needed to resume: weights, optimiser, RNG states, counters."""
        return {
            "model": self.net.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "numpy_rng": np.random.get_state(),
            "global_step": self.global_step,
            "updates": self.updates,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`. The environments are not checkpointed: they restart with
        fresh episodes from a seed derived from the update count (same step, weights and
        optimiser; not bit for bit the same episodes)."""
        self.net.load_state_dict(state["model"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        np.random.set_state(tuple(state["numpy_rng"]))
        self.global_step = int(state["global_step"])
        self.updates = int(state["updates"])
        self._last_step_mark = self.global_step
        self.reset_envs(self.cfg.seed + 7919 * self.updates)

    # --------------------------------------------------------------- reporting -----
    def take_train_stats(self) -> dict:
        """Training-episode statistics and expert involvement since the last call."""
        s = self.stats.summary(self.cfg.max_steps)
        followed, asked, top = self.follow_counts.tolist()
        s["expert_follow_rate"] = followed / asked if asked else 0.0
        s["expert_top_rate"] = top / asked if asked else 0.0
        s["expert_step_fraction"] = self.expert_steps / max(1, self.global_step - self._last_step_mark)
        self._last_step_mark = self.global_step
        self.stats = EpisodeStats()
        self.follow_counts.zero_()
        self.expert_steps = 0
        return s
