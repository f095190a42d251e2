"""Expert training by DAgger: supervised cloning of an environment's scripted oracle.

The paper's experts are other labs' MDRL-trained models. At the CPU scale PPO does not learn
target localization from its sparse reward (docs/reproduction/report.md), and behavioural
cloning inside the PPO loop (``il`` with R_E = 1) trains only on the oracle's own states, so
its clones wander off and barely beat a random team. DAgger (Ross, Gordon and Bagnell, 2011)
fixes exactly that covariate shift:

1. iteration i plays ``rollout_len`` batched steps in ``num_envs`` environments; each agent
   takes the oracle's best move with probability beta_i = ``beta_decay`` ** i, else a move
   sampled from the current policy (so later data comes from the states the clone visits);
2. every observation is labelled with the oracle's *set* of equally best valid moves
   (ties are common: N and NE can both shorten a path) and added to the dataset;
3. ``grad_steps`` Adam minibatches fit the policy to the aggregated dataset (cross-entropy
   against the uniform distribution over the best moves, invalid moves masked out).

The oracle sees what the agents do not (e.g. the target cell); the clone sees only the
agents' own observations, so what it learns is what those observations tell. The policy
is an ordinary :class:`medc_training.nets.ActorCritic` (the value head is untouched) and is
shipped as a normal policy bundle whose manifest says ``"method": "dagger"``.

Observations are stored as float16 (the maps are in [0, 1]) and the dataset keeps the
newest ``max_samples`` samples, so memory stays bounded at any scale.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from .bundle import save_bundle
from .config import RunConfig
from .evaluate import evaluate_policy, net_policy
from .nets import make_actor_critic, masked_logits
from .ppo import EVAL_SEED_OFFSET, make_env_for, seed_everything
from .runner import BUNDLE, observation_section

CSV_COLUMNS = (
    "iteration",
    "step",
    "samples",
    "beta",
    "bc_loss",
    "episode_length",
    "success_rate",
    "greedy_length",
    "greedy_success",
    "sampled_length",
    "sampled_success",
    "wall_time",
)


#: The field a clone config dict lacks when it was recorded while ``eval_every`` counted DAgger
#: iterations (the field came in when it started counting training steps): CloneConfig.upgrade.
_ITERATION_EVAL_MARK = "torch_threads"


@dataclass
class CloneConfig(RunConfig):
    """One DAgger run. Field docstrings are the documentation: the environment fields come from
    :class:`medc_training.config.EnvironmentConfig`, the fields every run shares (arch, total_steps,
    num_envs, lr, eval_every and the other evaluation fields, seed, device, torch_threads) from
    :class:`medc_training.config.RunConfig`; below, their defaults for cloning (the CPU scale's grid)
    and the fields of DAgger alone."""

    # RunConfig's fields with cloning's defaults (each field is documented on RunConfig).
    grid: int = 13
    max_steps: int = 50
    total_steps: int = 64_000
    num_envs: int = 64
    lr: float = 1e-3
    eval_every: int = 25_600  # every 4 iterations of the default 64 x 100 training steps
    eval_episodes: int = 128
    eval_envs: int = 32

    # --- DAgger ----------------------------------------------------------------------------
    rollout_len: int = 100
    """Batched steps collected per iteration (num_envs * rollout_len training steps)."""
    beta_decay: float = 0.5
    """beta_i = beta_decay ** i: probability that an agent takes the oracle's move in iteration i."""
    grad_steps: int = 500
    """Adam minibatches after each iteration."""
    batch_size: int = 256
    """Samples per minibatch."""
    max_samples: int = 200_000
    """Dataset cap: the newest samples are kept."""

    @property
    def steps_per_iteration(self) -> int:
        """Training steps one DAgger iteration collects."""
        return self.num_envs * self.rollout_len

    @property
    def iterations(self) -> int:
        """DAgger iterations the step budget buys (at least one)."""
        return max(1, math.ceil(self.total_steps / self.steps_per_iteration))

    def evaluation_points(self) -> list[int]:
        """The training steps after which the run evaluates: the end of each iteration that reaches
        a multiple of ``eval_every``, and the end of the last iteration."""
        per, last = self.steps_per_iteration, self.iterations
        return [i * per for i in range(1, last + 1)
                if i == last or i * per // self.eval_every > (i - 1) * per // self.eval_every]

    def validate(self) -> CloneConfig:
        """Raise ValueError naming the bad field; returns self."""
        self.check_run_fields(("total_steps", "num_envs", "rollout_len", "batch_size", "max_samples",
                               "eval_episodes", "eval_envs", "eval_every"))
        if self.grad_steps < 0 or self.walls < 0:
            raise ValueError("grad_steps and walls must be >= 0")
        if not 0.0 <= self.beta_decay <= 1.0:
            raise ValueError(f"beta_decay must be in [0, 1], got {self.beta_decay}")
        if not self.lr > 0:
            raise ValueError(f"lr must be > 0, got {self.lr}")
        return self

    @classmethod
    def upgrade(cls, data: dict) -> dict:
        """A clone config recorded while ``eval_every`` counted DAgger iterations (it has no
        ``torch_threads``) reads with the same evaluation points: ``eval_every`` iterations of
        ``num_envs * rollout_len`` training steps each."""
        if _ITERATION_EVAL_MARK in data or "eval_every" not in data:
            return data
        per = int(data.get("num_envs", cls.num_envs)) * int(data.get("rollout_len", cls.rollout_len))
        return {**data, "eval_every": int(data["eval_every"]) * per}


def best_moves(mask: torch.Tensor, scores: torch.Tensor) -> torch.Tensor:
    """bool [..., A]: the valid moves whose oracle score equals the best valid score."""
    s = scores.masked_fill(~mask, -1e9)
    return (s >= s.max(-1, keepdim=True).values - 1e-6) & mask


def clone_loss(logits: torch.Tensor, mask: torch.Tensor, best: torch.Tensor) -> torch.Tensor:
    """Cross-entropy of the masked policy against the uniform distribution over ``best``."""
    target = best.float()
    target = target / target.sum(-1, keepdim=True).clamp_min(1.0)
    logp = torch.log_softmax(masked_logits(logits, mask), -1)
    return -(target * logp.masked_fill(~mask, 0.0)).sum(-1).mean()


class _Dataset:
    """Aggregated (observation, mask, best-move set) samples, newest ``cap`` kept."""

    def __init__(self, obs_shape: tuple, num_actions: int, cap: int, device: torch.device) -> None:
        self.obs = torch.zeros((cap, *obs_shape), dtype=torch.float16, device=device)
        self.mask = torch.zeros((cap, num_actions), dtype=torch.bool, device=device)
        self.best = torch.zeros((cap, num_actions), dtype=torch.bool, device=device)
        self.cap, self.size, self.head = cap, 0, 0

    def add(self, obs: torch.Tensor, mask: torch.Tensor, best: torch.Tensor) -> None:
        n = obs.shape[0]
        if n >= self.cap:
            obs, mask, best, n = obs[-self.cap :], mask[-self.cap :], best[-self.cap :], self.cap
        idx = (torch.arange(n, device=self.obs.device) + self.head) % self.cap
        self.obs[idx] = obs.to(torch.float16)
        self.mask[idx] = mask
        self.best[idx] = best
        self.head = (self.head + n) % self.cap
        self.size = min(self.cap, self.size + n)

    def sample(self, batch: int, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
        idx = torch.randint(0, self.size, (batch,), generator=generator).to(self.obs.device)
        return self.obs[idx].float(), self.mask[idx], self.best[idx]


def clone_oracle(
    cfg: CloneConfig, out_dir: str | Path, progress: bool = False, bundle_to: str | Path | None = None
) -> dict:
    """Run DAgger for ``cfg``; write metrics.csv, learning_curve.png, policy.safetensors, summary.json.

    Returns the summary (final greedy / sampled episode lengths, a random team's, timings).
    """
    cfg.validate()
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    seed_everything(cfg.seed)
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise ValueError("device 'cuda' requested but torch.cuda.is_available() is False")
    env = make_env_for(cfg, cfg.num_envs, cfg.seed, False)
    if not hasattr(env, "oracle_action_scores"):
        raise ValueError(f"environment {cfg.env!r} has no oracle to clone")
    obs_shape = tuple(env.obs_shape)
    net = make_actor_critic(cfg.arch, obs_shape, env.num_actions, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    gen = torch.Generator().manual_seed(cfg.seed + 7)
    data = _Dataset(obs_shape, env.num_actions, cfg.max_samples, device)
    policy = net_policy(net, device)
    eval_seed = cfg.seed + EVAL_SEED_OFFSET

    def evaluate(pol, greedy: bool) -> dict:
        return evaluate_policy(
            make_env_for(cfg, cfg.eval_envs, eval_seed, False), pol, cfg.eval_episodes, greedy, eval_seed
        )

    with open(out / "metrics.csv", "w", newline="") as f:
        csv.DictWriter(f, fieldnames=CSV_COLUMNS).writeheader()
    per_iteration = cfg.steps_per_iteration
    evaluate_after = set(cfg.evaluation_points())
    bar = None
    if progress:
        from .console import progress_bar

        bar = progress_bar(cfg.iterations * per_iteration, unit="step")
    obs, mask = env.reset(seed=cfg.seed)
    start = time.perf_counter()
    steps = 0
    row: dict = {}
    losses: list[float] = []  # minibatch losses since the last metrics row
    try:
        for it in range(cfg.iterations):
            beta = cfg.beta_decay**it
            obs, mask = _collect(env, net, data, obs, mask, beta, cfg.rollout_len, gen)
            steps += per_iteration
            losses += _fit(net, opt, data, cfg, gen)
            if bar is not None:
                bar.update(per_iteration)
            if steps not in evaluate_after:
                continue
            greedy, sampled = evaluate(policy, True), evaluate(policy, False)
            row = _metrics_row(cfg, it, steps, data.size, beta, losses, greedy, sampled, start)
            with open(out / "metrics.csv", "a", newline="") as f:
                csv.DictWriter(f, fieldnames=CSV_COLUMNS).writerow(row)
            losses.clear()
            if bar is not None:
                bar.set_postfix(  # shown at the next redraw (console.progress_bar's pace in a log)
                    greedy=f"{greedy['episode_length']:.1f}", sampled=f"{sampled['episode_length']:.1f}",
                    refresh=False,
                )
    finally:
        if bar is not None:
            bar.close()
    return _finish(cfg, out, env, net, row, evaluate(None, False), steps, bundle_to)


def _collect(env, net, data: _Dataset, obs: torch.Tensor, mask: torch.Tensor, beta: float, rollout_len: int,
             gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Play ``rollout_len`` batched steps, each agent taking the oracle's best move with probability
    ``beta`` and else a move sampled from the clone, and label every observation with the oracle's
    set of best moves. Returns the last observation and mask."""
    b, n, a = env.num_envs, env.num_agents, env.num_actions
    obs_shape = tuple(env.obs_shape)
    net.eval()
    for _ in range(rollout_len):
        flat_obs, flat_mask = obs.reshape(b * n, *obs_shape), mask.reshape(b * n, a)
        scores = env.oracle_action_scores().reshape(b * n, a)
        data.add(flat_obs, flat_mask, best_moves(flat_mask, scores))
        with torch.no_grad():
            probs = torch.softmax(masked_logits(net(flat_obs)[0], flat_mask), -1).cpu()
        own = torch.multinomial(probs, 1, generator=gen).squeeze(-1)
        oracle = scores.masked_fill(~flat_mask, -1e9).argmax(-1).cpu()
        take_oracle = torch.rand(own.shape, generator=gen) < beta
        step = env.step(torch.where(take_oracle, oracle, own).view(b, n).to(env.device))
        obs, mask = step.obs, step.mask
    return obs, mask


def _fit(net, opt: torch.optim.Optimizer, data: _Dataset, cfg: CloneConfig,
         gen: torch.Generator) -> list[float]:
    """``cfg.grad_steps`` Adam minibatches on the aggregated dataset; their losses."""
    net.train()
    losses = []
    for _ in range(cfg.grad_steps):
        o, m, b = data.sample(cfg.batch_size, gen)
        loss = clone_loss(net(o)[0], m, b)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    net.eval()
    return losses


def _metrics_row(cfg: CloneConfig, it: int, steps: int, samples: int, beta: float, losses: list[float],
                 greedy: dict, sampled: dict, start: float) -> dict:
    """One metrics.csv row (:data:`CSV_COLUMNS`); the headline columns follow ``cfg.eval_greedy``."""
    head = greedy if cfg.eval_greedy else sampled
    return {
        "iteration": it,
        "step": steps,
        "samples": samples,
        "beta": beta,
        "bc_loss": sum(losses) / len(losses) if losses else math.nan,
        "episode_length": head["episode_length"],
        "success_rate": head["success_rate"],
        "greedy_length": greedy["episode_length"],
        "greedy_success": greedy["success_rate"],
        "sampled_length": sampled["episode_length"],
        "sampled_success": sampled["success_rate"],
        "wall_time": time.perf_counter() - start,
    }


def _finish(cfg: CloneConfig, out: Path, env, net, row: dict, rand: dict, steps: int,
            bundle_to: str | Path | None) -> dict:
    """Write the bundle (and its copy at ``bundle_to``), the learning curve and summary.json from the
    last metrics ``row`` and the random team's evaluation ``rand``; return the summary."""
    metrics = {
        "mean_episode_length": row["episode_length"],
        "success_rate": row["success_rate"],
        "greedy_episode_length": row["greedy_length"],
        "greedy_success_rate": row["greedy_success"],
        "sampled_episode_length": row["sampled_length"],
        "sampled_success_rate": row["sampled_success"],
        "random_episode_length": rand["episode_length"],
        "random_success_rate": rand["success_rate"],
    }
    attrs = dict(getattr(env, "attributes", None) or cfg.env_attributes())
    manifest = {
        "application": cfg.env,
        "description": f"DAgger clone of the scripted oracle for {cfg.env} "
        + ", ".join(f"{k}={v}" for k, v in attrs.items()),
        "environment": attrs,
        **observation_section(env),
        "training": {
            "method": "dagger",
            "steps": steps,
            "seed": cfg.seed,
            "arch": cfg.arch,
            "iterations": cfg.iterations,
            "grad_steps": cfg.grad_steps,
            "beta_decay": cfg.beta_decay,
            "evaluation": cfg.evaluation,
        },
        "metrics": {k: float(v) for k, v in metrics.items()},
    }
    save_bundle(out / BUNDLE, net, manifest)
    if bundle_to is not None:
        Path(bundle_to).parent.mkdir(parents=True, exist_ok=True)
        save_bundle(bundle_to, net, manifest)
    summary = {
        "config": cfg.to_dict(),
        "steps": steps,
        "iterations": cfg.iterations,
        "train_seconds": row["wall_time"],
        "final_episode_length": row["episode_length"],
        "final_success_rate": row["success_rate"],
        "metrics": metrics,
        "bundle": BUNDLE,
    }
    try:
        from .plots import plot_learning_curve

        plot_learning_curve(
            out / "metrics.csv",
            out / "learning_curve.png",
            title=f"{cfg.env} A{cfg.agents} DAgger ({cfg.arch})",
            greedy=cfg.eval_greedy,
        )
        summary["learning_curve"] = "learning_curve.png"
    except Exception as exc:  # a plotting failure must not lose a finished run
        summary["learning_curve_error"] = str(exc)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    return summary
