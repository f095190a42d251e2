"""One documented configuration for every training method (CleanRL-style dataclass).

Defaults are the paper's hyperparameter table (PPO: lr 3e-4, clip 0.2, entropy 0.01,
γ 0.99, λ 0.95, horizon 4000, 20 epochs; MEDC: R_E 0.1, Q 0.05, R_S = QoS_i / Σ QoS_j) and
its evaluation protocol (every 40,000 training steps, 4,000 greedy test steps). The CPU
scale used by tests and the reproduction report overrides a few of them through
:func:`cpu_scale`; every override is listed there.

Step counting: one *training step* is one step of one environment (the whole team moves
once). With ``num_envs`` environments stepping together, a rollout of ``horizon`` training
steps is ``horizon // num_envs`` batched steps, and it holds ``horizon * agents`` samples
(each agent's transition is a sample; centralized learning, decentralized execution).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from .envs import DEFAULT_APPLICATION, application

METHODS = ("sparse", "medc", "rs", "il", "frl")


@dataclass
class EnvironmentConfig:
    """The environment a run plays (every :class:`RunConfig` holds one)."""

    env: str = DEFAULT_APPLICATION
    """Application: one of medc_training.envs.APPLICATIONS."""
    agents: int = 3
    """Team size (the y in AyWz)."""
    walls: int = 2
    """Number of wall segments (the z in AyWz); target localization only."""
    grid: int = 30
    """Side of the square grid (the paper's G = 30)."""
    max_steps: int = 100
    """Episode length limit; reaching it truncates the episode (PPO bootstraps it)."""
    env_options: dict = field(default_factory=dict)
    """Extra keyword options passed to make_batched (e.g. customers for fleet coordination)."""
    observation: str | None = None
    """The observation (medc_training.envs.observation): 'maps' (the application's absolute maps),
    'egoR' (agent-centred windows), and for an application with a source estimate 'maps+estimate',
    'egoR+estimate', 'maps+posterior', 'egoR+posterior', 'maps+estimate+posterior',
    'egoR+estimate+posterior'. None: the application's default (``Application.default_observation``). An
    application whose observation is not a config field (``Application.observation_in_config``)
    takes it only when it differs from the default application's default, the value scales name
    (or through ``env_options``)."""

    def make_options(self, reward_shaping: bool = False) -> dict:
        """The keyword options of :func:`medc_training.envs.make_batched` this config describes
        (besides num_envs, device and seed). Raises ValueError when ``observation`` and
        ``env_options['observation']`` disagree."""
        app = application(self.env)
        accepted = app.options()
        options = dict(self.env_options)
        options.update(agents=self.agents, grid=self.grid, max_steps=self.max_steps)
        if "walls" in accepted:
            options["walls"] = self.walls
        if "reward_shaping" in accepted:
            options["reward_shaping"] = reward_shaping
        observation = app.default_observation if self.observation is None else self.observation
        # The scales name the default application's default observation; another application
        # keeps its own default unless told otherwise.
        scale_default = application(DEFAULT_APPLICATION).default_observation
        given = app.observation_in_config or self.observation not in (None, scale_default)
        if given and options.setdefault("observation", observation) != observation:
            raise ValueError(f"observation {observation!r} and env_options observation "
                             f"{options['observation']!r} disagree; give one")
        return options

    def env_attributes(self) -> dict:
        """The environment's descriptive features as stored in bundle manifests."""
        attrs = {"agents": self.agents, "grid": self.grid, "max_steps": self.max_steps}
        if "walls" in application(self.env).options():
            attrs["walls"] = self.walls
        attrs.update(self.env_options)
        return attrs


@dataclass
class RunConfig(EnvironmentConfig):
    """What every run configuration shares: :class:`TrainConfig` (PPO and the methods built on it)
    and :class:`medc_training.dagger.CloneConfig` (DAgger cloning of an oracle). Each field is
    defined here once; a subclass only gives some of them other defaults.
    """

    arch: str = "lenet5"
    """Actor-critic architecture name from medc_training.nets.ARCHITECTURES."""
    total_steps: int = 20_000_000
    """Training steps of the whole run (environment steps: one step = the whole team moves once)."""
    num_envs: int = 16
    """Environments stepped together by the batched core while training."""
    lr: float = 3e-4
    """Adam learning rate."""

    # --- evaluation ----------------------------------------------------------------------
    eval_every: int = 40_000
    """E: evaluate every E training steps. PPO (TrainConfig) also evaluates once before training;
    DAgger (CloneConfig) evaluates after each iteration that reaches a multiple of E."""
    eval_episodes: int = 64
    """Episodes per evaluation: a fixed set drawn from the evaluation seed, each played to its end
    (success or max_steps) by medc_training.evaluate.play_episodes, split over eval_envs
    environments (ceil(eval_episodes / eval_envs) rounds). Every evaluation of a run, and every
    method with the same seed, plays the same episodes, and none is left out for being long.
    TrainConfig only, 0: the legacy *window* of the committed reproduction, which the research
    harness keeps (medc_lab.window): eval_steps test steps and the mean length of the episodes
    that finished inside them, which leans short. A TrainConfig recorded before this field
    existed means 0 (see TrainConfig.from_dict)."""
    eval_envs: int = 16
    """Environments for evaluation."""
    eval_greedy: bool = True
    """Test actions are the policy's argmax (True) or sampled from it (False); the run's headline
    curve. A memoryless greedy policy repeats itself forever in coverage tasks (fleet coordination,
    maze cleaning: the same observation gives the same move), so those are evaluated on sampled
    actions."""

    # --- run -------------------------------------------------------------------------------
    seed: int = 0
    """Seeds torch, numpy and the environments; runs are reproducible on one device."""
    device: str = "cpu"
    """cpu or cuda."""
    torch_threads: int = 0
    """torch intra-op threads (0 = leave torch's default)."""

    def check_run_fields(self, at_least_one: tuple[str, ...]) -> None:
        """The checks every run configuration makes: a device torch can name, and the environment's
        agents, grid and max_steps plus ``at_least_one`` all >= 1. Raises ValueError naming the bad
        field."""
        if self.device not in ("cpu", "cuda") and not self.device.startswith("cuda:"):
            raise ValueError(f"device must be 'cpu' or 'cuda', got {self.device!r}")
        for name in ("agents", "grid", "max_steps", *at_least_one):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.torch_threads < 0:
            raise ValueError(f"torch_threads must be >= 0, got {self.torch_threads}")

    @property
    def evaluation(self) -> dict:
        """The evaluator of this config, as recorded in bundle manifests: the fixed episodes,
        ``{"evaluator": "episodes", "episodes", "envs", "greedy"}``."""
        return {"evaluator": "episodes", "episodes": self.eval_episodes, "envs": self.eval_envs,
                "greedy": self.eval_greedy}

    def to_dict(self) -> dict:
        """JSON-able copy (for checkpoints, manifests and summaries)."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict):
        """Inverse of to_dict; unknown keys are an error, not silently dropped. A dict recorded by
        an earlier version reads as :meth:`upgrade` says."""
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - known
        if unknown:
            raise ValueError(f"unknown config fields {sorted(unknown)}; known: {sorted(known)}")
        # A dict recorded before ``observation`` existed took the default application's default.
        data = {"observation": application(DEFAULT_APPLICATION).default_observation, **data}
        return cls(**cls.upgrade(data))

    @classmethod
    def upgrade(cls, data: dict) -> dict:
        """The fields of a dict recorded by an earlier version, in today's meaning (none change here)."""
        return data


#: The evaluator every run recorded before ``eval_episodes`` existed used (and the committed
#: reproduction keeps using, see medc_lab.plan): the window of eval_steps (medc_lab.window).
LEGACY_EVAL = {"eval_episodes": 0}


@dataclass
class TrainConfig(RunConfig):
    """Everything one training run needs. Field docstrings are the documentation.

    The environment fields (env, agents, walls, grid, max_steps, env_options, observation) come
    first, from :class:`EnvironmentConfig`, then the fields every run shares (arch, total_steps,
    num_envs, lr, the evaluation, seed, device, torch_threads), from :class:`RunConfig`, whose
    defaults here are the paper's.
    """

    # --- method ----------------------------------------------------------------------
    method: str = "sparse"
    """sparse (MDRL-sparse), medc, rs (BFS reward shaping), il (IL-assisted RL), frl (FedAvg)."""
    expert_rate: float = 0.1
    """R_E: probability that an episode is expert-guided (MEDC and IL)."""
    q_threshold: float = 0.05
    """Q: an expert action is followed only if the agent's own probability of it is >= Q."""

    # --- PPO (paper's hyperparameter table; lr and num_envs are RunConfig's) ------------
    horizon: int = 4000
    """H: training steps collected per PPO update (split over num_envs)."""
    epochs: int = 20
    """Optimisation epochs over each rollout."""
    minibatches: int = 4
    """Minibatches per epoch (over the horizon * agents samples)."""
    gamma: float = 0.99
    """Discount factor γ."""
    gae_lambda: float = 0.95
    """GAE λ."""
    clip: float = 0.2
    """PPO clipping parameter ε."""
    ent_coef: float = 0.01
    """Entropy coefficient c2."""
    lr_anneal_steps: int = 0
    """Learning-rate schedule: 0 keeps ``lr`` constant (the paper's); N > 0 lowers it linearly from
    ``lr`` at step 0 to 0 at training step N (CleanRL's annealing, with N the whole budget of a run
    trained in ``--resume`` pieces), then keeps it at 0."""
    vf_coef: float = 0.5
    """Value-loss coefficient c1 (the paper leaves it at PPO's usual value)."""
    max_grad_norm: float = 0.5
    """Global gradient-norm clip."""
    norm_adv: bool = True
    """Normalise advantages per minibatch."""
    bc_coef: float = 1.0
    """Weight of the behavioural-cloning loss on expert samples (IL-assisted RL)."""

    # --- FRL -----------------------------------------------------------------------------
    frl_users: list = field(default_factory=list)
    """FRL: one dict of environment attributes per user (agents/walls/...); the first user
    whose attributes equal this run's environment is the one whose curve is reported."""
    frl_every: int = 1
    """K: FedAvg of the users' parameters every K updates."""

    # --- evaluation (the rest is RunConfig's) ----------------------------------------------
    eval_steps: int = 4_000
    """T: test steps per evaluation (split over eval_envs); used only by the legacy window
    (eval_episodes = 0)."""

    def validate(self) -> TrainConfig:
        """Raise ValueError naming the bad field; returns self for chaining."""
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {self.method!r}")
        self.check_run_fields(("num_envs", "horizon", "epochs", "minibatches", "eval_envs", "frl_every"))
        if (self.walls < 0 or self.total_steps < 0 or self.eval_steps < 0 or self.eval_every < 0
                or self.eval_episodes < 0 or self.lr_anneal_steps < 0):
            raise ValueError("walls, total_steps, eval_episodes, eval_steps, eval_every and lr_anneal_steps "
                             "must be >= 0")
        if self.horizon < self.num_envs:
            raise ValueError(f"horizon ({self.horizon}) must be >= num_envs ({self.num_envs})")
        if not 0.0 <= self.expert_rate <= 1.0:
            raise ValueError(f"expert_rate (R_E) must be in [0, 1], got {self.expert_rate}")
        if not 0.0 <= self.q_threshold <= 1.0:
            raise ValueError(f"q_threshold (Q) must be in [0, 1], got {self.q_threshold}")
        if not 0.0 < self.gamma <= 1.0:
            raise ValueError(f"gamma (the discount) must be in (0, 1], got {self.gamma}")
        return self

    @property
    def rollout_len(self) -> int:
        """Batched steps per rollout (horizon split over the environments)."""
        return max(1, self.horizon // self.num_envs)

    @property
    def steps_per_update(self) -> int:
        """Training steps actually collected per update."""
        return self.rollout_len * self.num_envs

    @property
    def evaluation(self) -> dict:
        """The evaluator of this config, as recorded in bundle manifests: the fixed episodes
        (RunConfig's) or the legacy window (``{"evaluator": "window", "steps", "envs", "greedy"}``)."""
        if self.eval_episodes:
            return super().evaluation
        return {"evaluator": "window", "steps": self.eval_steps, "envs": self.eval_envs,
                "greedy": self.eval_greedy}

    @classmethod
    def upgrade(cls, data: dict) -> dict:
        """A dict without ``eval_episodes`` was recorded before that field existed, with the window
        evaluator, so it reads as ``eval_episodes = 0`` (LEGACY_EVAL), not as today's default."""
        return {**LEGACY_EVAL, **data}


# The CPU scale: what changes from the paper so that the whole reproduction runs on a
# 2-core machine in well under an hour. Everything not listed keeps the paper's value.
CPU_SCALE = {
    # 13 is the smallest grid on which the environment accepts 3 walls (A1W3, A2W3, A3W3).
    "grid": 13,
    "max_steps": 50,
    "num_envs": 32,
    "horizon": 1024,
    "epochs": 4,
    "minibatches": 4,
    "eval_every": 4096,
    "eval_steps": 1600,
    "eval_envs": 32,
    # On 2 CPU cores the MLP trains ~4x faster than LeNet-5 at this size (measured with
    # medc-bench train); LeNet-5 remains the default at the paper scale and experts mix both.
    "arch": "mlp",
    # The observation MDRL-sparse learns from at this budget (measured: docs/environments.md).
    "observation": "ego6+estimate",
}

# The paper's scale, for a GPU.
PAPER_SCALE = {
    "grid": 30,
    "max_steps": 100,
    "num_envs": 50,          # 50 x 80 steps = the paper's horizon of exactly 4000
    "horizon": 4000,
    "epochs": 20,
    "minibatches": 4,
    "eval_every": 40_000,
    "eval_steps": 4_000,
    "eval_envs": 20,         # 200 steps each, so a 100-step episode always finishes
    "arch": "lenet5",
    "total_steps": 20_000_000,
    # The paper's scale reproduces the paper: its 5 absolute maps (at the CPU scale no learner
    # learns from them; with 2x10^7 steps on a GPU the paper reports that PPO does).
    "observation": "maps",
}

# The rare-reward regime of docs/reproduction/claims/PROTOCOL.md (fixed before its runs): the
# realistic sensing preset on 40x40 cells with 50-step episodes, where random play finds the
# source in 9% of episodes. Evaluated every 16,384 steps on 64 fixed episodes.
CLAIMS_SCALE = {
    **CPU_SCALE,
    "grid": 40,
    "env_options": {"sensing": "realistic"},
    "eval_every": 16_384,
    "eval_envs": 64,
    "eval_episodes": 64,
}

SCALES = {"cpu": CPU_SCALE, "paper": PAPER_SCALE, "claims": CLAIMS_SCALE}


def scaled_config(scale: str, **overrides) -> TrainConfig:
    """A TrainConfig at a named scale ('cpu', 'paper' or 'claims') with overrides applied."""
    if scale not in SCALES:
        raise ValueError(f"scale must be one of {sorted(SCALES)}, got {scale!r}")
    values = dict(SCALES[scale])
    values.update(overrides)
    return TrainConfig(**values).validate()
