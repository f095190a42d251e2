"""`medc-demo` (what `make demo` runs): the paper's framework time sequence, end to end.

On the embedded defaults (an in-process Ethereum chain, a local IPFS-compatible content store):

1. users register with the Users Manager Contract;
2. owners share expert bundles trained by this code (models/claims/experts): each bundle goes to
   the content store and is added to the Models Manager Contract with its environment details;
3. a requester with an A3W2 environment asks for experts, pays, and gets them allocated by QoS;
   the bundles are fetched by CID and verified;
4. the requester trains with MEDC (the experts weighted by R_S = QoS_i / sum QoS_j) and, for the
   same budget and seed, with the sparse reward alone, where reward is rare (REGIME: the realistic
   preset on 40x40 cells, 50-step episodes; random moves find the source in about one episode in
   ten), the regime where borrowed experts speed learning up;
5. the requester reviews each expert (by how well it plays the requester's environment);
   reputations change; owners withdraw their payments;
6. the ROS 2 graph (simulator + one policy node per agent, separate processes over DDS) runs
   the newly trained policy for a few episodes, printed live, then infotaxis on the same episodes
   (the classical searcher a user would field there, which no learned team has beaten yet), then
   the shipped team (models/team) in the regime it was trained for, then the field benchmark's
   20 x 20 world (BENCH_CONFIG): the shipped benchmark team, which beats the strongest classical
   searcher there, and that searcher (BENCH_SEARCHER) on the same episodes;
7. a summary, a Markdown report with figures, and one JSON line.

``--quick`` shrinks the budgets (the end-to-end test runs it).
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from medc_common.ros_env import repo_root
from medc_training.envs.names import DEFAULT_APPLICATION

ETHER = 10**18
PRICE_WEI = ETHER // 100  # 0.01 ETH per allocated model
APPLICATION = DEFAULT_APPLICATION


class Narrator:
    """Prints numbered steps with elapsed time, so a person can follow the run live."""

    def __init__(self, quiet: bool = False) -> None:
        self.quiet = quiet
        self.t0 = time.monotonic()
        self.timings: dict[str, float] = {}
        self._step: str | None = None
        self._step_t = self.t0

    def step(self, title: str) -> None:
        now = time.monotonic()
        if self._step is not None:
            self.timings[self._step] = round(now - self._step_t, 2)
        self._step, self._step_t = title, now
        if not self.quiet:
            print(f"\n\033[1m[{now - self.t0:6.1f}s] {title}\033[0m", flush=True)

    def say(self, text: str) -> None:
        if not self.quiet:
            print(f"    {text}", flush=True)

    def finish(self) -> float:
        now = time.monotonic()
        if self._step is not None:
            self.timings[self._step] = round(now - self._step_t, 2)
        return now - self.t0


def _eth(wei: int) -> str:
    return f"{wei / ETHER:.4f} ETH"


def _features(manifest: dict) -> dict[str, int]:
    env = manifest.get("environment", {})
    return {"agents": int(env["agents"]), "walls": int(env["walls"])}


def play_bundle(bundle, agents: int, walls: int, cfg, episodes: int, seed: int) -> dict:
    """Greedy play of ``bundle`` for every agent of AyWz on ``episodes`` fixed episodes of the
    configuration ``cfg`` (its grid, episode cap and environment options), each played to its end;
    mean episode length and success rate (the summary of medc_training.evaluate.evaluate_policy)."""
    from medc_training.envs import make_batched
    from medc_training.evaluate import evaluate_policy

    env = make_batched(
        APPLICATION, num_envs=min(episodes, 32), seed=seed, agents=agents, walls=walls, grid=cfg.grid,
        max_steps=cfg.max_steps, observation=bundle.observation, **cfg.env_options,
    )
    return evaluate_policy(env, bundle, episodes, greedy=True, seed=seed)


def learning_score_of(metrics_csv: Path) -> float:
    """Mean evaluation episode length over a run's evaluations after step 0 (the reproduction
    report's learning score; lower = faster and better learning)."""
    from medc_training.metrics import read_metrics
    from medc_training.stats import learning_score

    return learning_score([r["episode_length"] for r in read_metrics(metrics_csv)])


def random_policy_length(
    agents: int, walls: int, grid: int, max_steps: int, episodes: int, seed: int, sensing: str | None = None
) -> float:
    """Mean episode length of uniformly random valid moves on ``episodes`` fixed episodes, each
    played to its end (the floor a trained team must beat), under ``sensing`` (None: the default)."""
    from medc_training.envs import make_batched
    from medc_training.evaluate import evaluate_policy

    env = make_batched(  # random moves need no observation: the cheapest one
        APPLICATION, num_envs=32, seed=seed, agents=agents, walls=walls, grid=grid, max_steps=max_steps,
        observation="maps", **({"sensing": sensing} if sensing else {}),
    )
    return evaluate_policy(env, None, episodes, greedy=False, seed=seed)["episode_length"]


def trajectory_png(bundle, cfg, seed: int, path: Path) -> dict:
    """Play one greedy episode in the ParallelEnv and draw the team's paths over the area
    (squares: start cells)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np
    from medc_training.envs import make_env
    from medc_training.envs.grid import action_deltas

    env = make_env(
        APPLICATION, agents=cfg.agents, walls=cfg.walls, grid=cfg.grid, max_steps=cfg.max_steps, seed=seed,
        observation=bundle.observation, **cfg.env_options,
    )
    obs, _ = env.reset(seed=seed)
    core = env.unwrapped.core  # the batched core (B = 1) under the PettingZoo wrapper
    # The core starts a new episode as soon as this one ends: take the layout now.
    start = core.state(0)
    walls = start.walls.cpu().numpy()
    ty, tx = start.target
    paths: list[list[tuple[int, int]]] = [[p] for p in start.positions]
    steps, success = 0, False
    agents = list(env.agents)
    while env.agents:
        batch = np.stack([obs[a]["observation"] for a in agents])
        masks = np.stack([obs[a]["action_mask"] for a in agents]).astype(bool)
        acts = bundle.act(batch, masks, greedy=True).tolist()
        before = core.state(0).positions
        obs, _, terms, truncs, _ = env.step({a: int(x) for a, x in zip(agents, acts)})
        steps += 1
        if any(terms.values()) or any(truncs.values()):
            success = any(terms.values())
            # The last move, from the positions before it (the core has already reset).
            deltas = action_deltas("cpu").tolist()
            for i, (pos, m) in enumerate(zip(before, masks)):
                dr, dc = deltas[acts[i]] if m[acts[i]] else (0, 0)
                paths[i].append((pos[0] + dr, pos[1] + dc))
            break
        for i, p in enumerate(core.state(0).positions):
            paths[i].append(p)
    fig, ax = plt.subplots(figsize=(5, 5))
    ax.imshow(walls, cmap="Greys", origin="upper")
    ax.plot(tx, ty, marker="*", color="red", markersize=18, label="target")
    for i, trail in enumerate(paths):
        ys, xs = zip(*trail)
        ax.plot(xs, ys, "-o", markersize=3, label=f"agent {i}")
        ax.plot(xs[0], ys[0], "s", color=ax.lines[-1].get_color(), markersize=7)
    ax.set_title(f"One episode with the trained team: {steps} steps, {'found' if success else 'not found'}")
    ax.legend(loc="upper right", fontsize=7)
    ax.set_xticks([])
    ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    env.close()
    return {"steps": steps, "success": success}


def curves_png(runs: dict[str, Path], path: Path, title: str) -> None:
    """Evaluation episode length against training steps, one line per run."""
    import csv

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    for name, csv_path in runs.items():
        with open(csv_path, newline="") as f:
            rows = list(csv.DictReader(f))
        ax.plot(
            [int(r["step"]) for r in rows],
            [float(r["episode_length"]) for r in rows],
            "-o",
            markersize=3,
            label=name,
        )
    ax.set_xlabel("training steps")
    ax.set_ylabel("mean episode length (greedy test)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


@dataclass
class _Demo:
    """What every phase of one demo run shares: its options, output folder, narrator and gas log."""

    args: argparse.Namespace
    out: Path
    root: Path
    say: Narrator
    quiet: bool
    gas: dict[str, list[int]] = field(default_factory=dict)

    def spent(self, fn: str, gas: int) -> None:
        self.gas.setdefault(fn, []).append(int(gas))


@dataclass
class _Users:
    """Phase 1: the registry and its registered users (three owners, one requester)."""

    reg: Any
    names: list[str]
    users: dict[str, Any]

    @property
    def owners(self) -> list[Any]:
        return [self.users[n] for n in self.names[:3]]

    @property
    def requester(self) -> Any:
        return self.users["requester"]

    def name_of(self, owner: Any) -> str:
        return self.names[self.owners.index(owner)]


@dataclass
class _Allocation:
    """Phase 3: what the requester paid for and fetched, and the reputations before it."""

    allocations: list[Any]
    experts: list[Any]
    qos_values: list[float]
    price: int
    r_s: list[float]
    qos_order_ok: bool
    model_rep_before: dict[int, float]
    owner_rep_before: dict[str, float]


@dataclass
class _Training:
    """Phase 4: MEDC and sparse on the requester's environment."""

    cfg: Any
    results: dict[str, dict]
    scores: dict[str, float]
    policy_paths: dict[str, Path]

    @property
    def medc_faster(self) -> bool:
        return self.scores["medc"] < self.scores["sparse"]


@dataclass
class _Settlement:
    """Phase 5: reviews, reputations after them, and the owners' withdrawals."""

    reviews: list[dict]
    model_reputations: list[dict]
    owner_reputations: list[dict]
    payments: list[dict]
    contract_balance: int


@dataclass
class _Graph:
    """Phase 6: the ROS 2 graph's runs and the random team's episode length."""

    random_len: float
    graph: dict[str, Any]
    shipped_team: dict[str, Any]
    #: The classical searcher (SEARCHER) on the new policy's episodes in the graph.
    searcher: dict[str, Any] = field(default_factory=lambda: {"skipped": True})
    #: The benchmark's world: the shipped benchmark team and BENCH_SEARCHER on the same episodes.
    benchmark: dict[str, Any] = field(default_factory=lambda: {"skipped": True})


TARGET = {"agents": 3, "walls": 2}
#: The regime the requester trains in: the training scale of docs/reproduction/claims/PROTOCOL.md
#: (the realistic preset on 40x40 cells, 50-step episodes, random moves finding the source in about
#: one episode in ten) and the experts cloned for it. There MEDC with proper experts led MDRL-sparse
#: on every one of 5 seeds (learning score over the first 100k steps 33-38 against 41-46 steps,
#: docs/reproduction/claims/runs), where on the paper-simple 13x13 sparse learns as fast alone.
REGIME = {"scale": "claims", "experts": ("models", "claims", "experts")}
#: The classical searcher the graph plays on the new policy's episodes: on the regime's 512 fixed
#: episodes infotaxis needs 17.4 steps and finds the source in 97% (docs/reproduction/claims), ahead of
#: every learned team, and the realistic graph's default (config/launch.yaml) is infotaxis.
SEARCHER = "infotaxis"
#: What one seed's MEDC-against-sparse comparison is, said wherever the demo reports it.
ONE_SEED = ("one seed: a measurement, not a verdict; docs/reproduction/claims/report.md has the claims "
            "over 5 seeds in this regime")
EXPERTS_REQUESTED = 3
#: The shipped team of the field benchmark's 20 x 20 world, as a launch config (its bundle, the
#: estimator's prior and the endgame it was judged with; models/README.md, "models/radbench/"): on the
#: benchmark's frozen episodes it takes 11.58 moves where BENCH_SEARCHER takes 14.20.
BENCH_CONFIG = ("models", "radbench", "g20-a3.yaml")
#: The strongest classical searcher there, played on the same episodes under its own model.
BENCH_SEARCHER = "infotaxis-exact"


def run(args: argparse.Namespace) -> dict[str, Any]:
    """The whole demo (module docstring): the seven phases in turn; returns the summary."""
    import torch
    from medc_training.outfiles import check_output_folder

    out = check_output_folder(args.out).resolve()  # a file, a device or a name too long: refused now
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(max(1, args.threads))
    quiet = bool(getattr(args, "quiet", False))
    demo = _Demo(args, out, repo_root(), Narrator(quiet=quiet), quiet)
    steps = args.steps or (40_960 if args.quick else 204_800)
    episodes = args.episodes or (5 if args.quick else 10)
    users = _register_users(demo)
    shared = _share_experts(demo, users)
    allocation = _request_experts(demo, users, shared)
    training = _train(demo, allocation, steps)
    settlement = _review_and_pay(demo, users, shared, allocation, training)
    graph = _run_graph_phase(demo, training, episodes)
    return _summarise(demo, allocation, training, settlement, graph)


def _register_users(demo: _Demo) -> _Users:
    from medc_registry.registry import Registry

    say = demo.say
    say.step("1. Users register with the Users Manager Contract (embedded chain, local IPFS store)")
    reg = Registry.embedded(str(demo.out / "ipfs-store"))
    for name, g in reg.deployment.gas.items():
        demo.spent(f"deploy {name}", g)
    say.say(
        f"chain: {reg.chain.description}; UsersManager {reg.deployment.users}, "
        f"ModelsManager {reg.deployment.models}"
    )
    names = ["lab-north (owner)", "lab-south (owner)", "lab-east (owner)", "requester"]
    users = {name: reg.as_user(i + 1) for i, name in enumerate(names)}
    for name, user in users.items():
        tx = user.register_user()
        demo.spent("addUser", tx.gas_used)
        say.say(f"{name:18s} {user.address}  reputation {user.user().reputation:.2f}  gas {tx.gas_used:,}")
    return _Users(reg, names, users)


def _share_experts(demo: _Demo, users: _Users) -> list[Any]:
    from medc_training.bundle import read_manifest

    demo.say.step("2. Owners share expert bundles: content store (CID) + Models Manager Contract")
    folder = demo.root.joinpath(*REGIME["experts"])
    expert_files = sorted(folder.glob("*.safetensors"))
    if not expert_files:
        raise RuntimeError(f"{folder} holds no bundles; regenerate them (see models/README.md)")
    owners = users.owners
    shared = []
    for i, path in enumerate(expert_files):
        data = path.read_bytes()
        manifest = read_manifest(data)
        if manifest.get("application") != APPLICATION:
            continue
        feats = _features(manifest)
        owner = owners[i % len(owners)]
        model = owner.share_model(
            data,
            APPLICATION,
            feats,
            PRICE_WEI,
            description={"file": path.name, "arch": manifest["architecture"].get("name", "")},
        )
        demo.spent("addModel", owner.last_tx.gas_used)
        shared.append(model)
        demo.say.say(
            f"model {model.model_id}: {path.name:22s} A{feats['agents']}W{feats['walls']}  "
            f"{len(data) / 1024:6.0f} KiB  CID {model.cid}  by {users.name_of(owner)}"
        )
    return shared


def _request_experts(demo: _Demo, users: _Users, shared: list[Any]) -> _Allocation:
    from medc_training.bundle import load_bundle
    from medc_training.experts import BundleExpert
    from medc_training.qos import selection_weights

    say, requester, count = demo.say, users.requester, EXPERTS_REQUESTED
    say.step(f"3. The requester (A{TARGET['agents']}W{TARGET['walls']}) requests {count} experts and pays")
    model_rep_before = {m.model_id: m.reputation for m in shared}
    owner_rep_before = {users.name_of(o): o.user().reputation for o in users.owners}
    ids, price = requester.quote(APPLICATION, TARGET, count=count)
    say.say(f"quote: models {ids} for {_eth(price)}")
    allocations = requester.request_models(APPLICATION, TARGET, count=count, payment=price)
    demo.spent("allocateModels", requester.last_tx.gas_used)
    say.say(f"{'alloc':>5} {'model':>5} {'env':>6} {'D_m':>5} {'QoS':>8} {'price':>12}  CID")
    experts, qos_values = [], []
    for a in allocations:
        env = a.model.env_features
        q = a.qos if math.isfinite(a.qos) else float("inf")
        env_name = f"A{env['agents']}W{env['walls']}"
        say.say(
            f"{a.allocation_id:>5} {a.model_id:>5} {env_name:>6} "
            f"{a.distance:5.2f} {q:8.3f} {_eth(a.price_wei):>12}  {a.cid}"
        )
        data = requester.fetch(a.cid)  # verified against the CID before it is returned
        bundle = load_bundle(data)  # validated: data, never code
        experts.append(BundleExpert(bundle, name=f"model-{a.model_id}"))
        qos_values.append(q)
        say.say(
            f"      fetched {len(data):,} bytes, CID verified, bundle valid "
            f"({bundle.manifest['architecture'].get('name', '?')}, sha256 {bundle.sha256[:12]}...)"
        )
    qos_order_ok = all(qos_values[i] >= qos_values[i + 1] for i in range(len(qos_values) - 1))
    # R_S by the contract's rule (medc_training.qos): exact matches, if any, share the wheel by
    # Rep_owner * Rep_model, the order the contract gives them.
    rep_products = [a.model.reputation * requester.user(a.owner).reputation for a in allocations]
    r_s = selection_weights(qos_values, rep_products)
    say.say("R_S (roulette-wheel slices) = " + ", ".join(f"{x:.2f}" for x in r_s))
    return _Allocation(allocations, experts, qos_values, price, r_s, qos_order_ok, model_rep_before,
                       owner_rep_before)


def _regime_words(cfg) -> str:
    """The training regime in words, e.g. "the realistic preset, 40x40 cells, 50-step episodes"."""
    sensing = cfg.env_options.get("sensing", "paper-simple")
    return f"the {sensing} preset, {cfg.grid}x{cfg.grid} cells, {cfg.max_steps}-step episodes"


def _train(demo: _Demo, allocation: _Allocation, steps: int) -> _Training:
    from medc_training.config import scaled_config
    from medc_training.ppo import Trainer
    from medc_training.runner import run_training

    say, out, args = demo.say, demo.out, demo.args
    cfg = scaled_config(REGIME["scale"], agents=TARGET["agents"], walls=TARGET["walls"], method="medc",
                        total_steps=steps, seed=args.seed, torch_threads=1)
    say.step(f"4. The requester trains with MEDC for {steps:,} steps, and with the sparse reward alone "
             f"({_regime_words(cfg)})")
    # The sparse baseline runs beside MEDC as its own `medc-train` process (one core each).
    results: dict[str, dict] = {}
    policy_paths = {m: out / m / "policy.safetensors" for m in ("medc", "sparse")}
    sparse_cmd = [str(Path(sys.executable).parent / "medc-train"), "--scale", REGIME["scale"],
                  "--agents", str(TARGET["agents"]),
                  "--walls", str(TARGET["walls"]), "--method", "sparse", "--steps", str(steps),
                  "--seed", str(args.seed), "--threads", "1", "--quiet", "--overwrite",
                  "--out", str(out / "sparse")]
    t = time.monotonic()
    with subprocess.Popen(sparse_cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) as sparse:
        trainer = Trainer(cfg, allocation.experts, expert_weights=allocation.r_s)
        results["medc"] = run_training(trainer, cfg, out / "medc",
                                       progress=not (args.no_progress or demo.quiet), overwrite=True)
        results["medc"]["wall_s"] = round(time.monotonic() - t, 1)
        sparse_out, sparse_err = sparse.communicate()
    if sparse.returncode != 0:
        detail = sparse_err.strip()[-500:]
        raise RuntimeError(f"the sparse baseline failed ({' '.join(sparse_cmd)}): {detail}")
    results["sparse"] = json.loads(sparse_out.strip().splitlines()[-1])
    results["sparse"]["wall_s"] = round(time.monotonic() - t, 1)
    for method, summary in results.items():
        say.say(
            f"{method:6s}: final greedy episode length {summary['final_episode_length']:.1f}, "
            f"success {summary['final_success_rate']:.0%}, done after {summary['wall_s']:.0f} s"
        )
    scores = {m: learning_score_of(out / m / "metrics.csv") for m in ("medc", "sparse")}
    training = _Training(cfg, results, scores, policy_paths)
    say.say(
        f"learning score (mean greedy evaluation episode length over the run, lower = faster): MEDC "
        f"{training.scores['medc']:.2f}, sparse {training.scores['sparse']:.2f}: MEDC learned "
        f"{'faster' if training.medc_faster else 'no faster'} than sparse on this seed "
        f"({ONE_SEED})"
    )
    curves_png(
        {
            "MEDC (allocated experts)": out / "medc" / "metrics.csv",
            "MDRL-sparse": out / "sparse" / "metrics.csv",
        },
        out / "learning_curves.png",
        f"A3W2, grid {cfg.grid}: MEDC vs sparse, seed {args.seed}",
    )
    say.say(f"learning curves: {out / 'learning_curves.png'}")
    return training


def _review_and_pay(demo: _Demo, users: _Users, shared: list[Any], allocation: _Allocation,
                    training: _Training) -> _Settlement:
    say, requester, cfg = demo.say, users.requester, training.cfg
    say.step("5. The requester reviews the experts; reputations update; owners withdraw")
    reviews = []
    for a, expert in zip(allocation.allocations, allocation.experts):
        played = play_bundle(expert.bundle, TARGET["agents"], TARGET["walls"], cfg, episodes=32,
                             seed=demo.args.seed + 99)
        value = round(float(played["success_rate"]), 3)
        tx = requester.review(a.allocation_id, value)
        demo.spent("updateModelRep", tx.gas_used)
        reviews.append({"allocation": a.allocation_id, "model": a.model_id, "review": value,
                        "expert_success_on_A3W2": played["success_rate"]})
        say.say(f"model {a.model_id}: success {played['success_rate']:.0%} on A3W2 -> review {value:.3f}")
    rep_table = []
    for m in shared:
        after = users.reg.model(m.model_id)
        rep_table.append({"model": m.model_id, "before": allocation.model_rep_before[m.model_id],
                          "after": after.reputation})
    for row in rep_table:
        if row["before"] != row["after"]:
            say.say(f"model {row['model']} reputation {row['before']:.3f} -> {row['after']:.3f}")
    owner_reps, payments = [], []
    for o in users.owners:
        name = users.name_of(o)
        rep_after = o.user().reputation
        owner_reps.append({"owner": name, "before": allocation.owner_rep_before[name], "after": rep_after})
        owed = o.owed()
        withdrawn = o.withdraw() if owed else 0
        if owed:
            demo.spent("withdraw", o.last_tx.gas_used)
        payments.append({"owner": name, "withdrawn_wei": withdrawn})
        say.say(
            f"{name:18s} reputation {allocation.owner_rep_before[name]:.3f} -> {rep_after:.3f}; "
            f"withdrew {_eth(withdrawn)}"
        )
    contract_balance = users.reg.chain.balance(users.reg.deployment.models)
    say.say(f"Models Manager balance after withdrawals: {_eth(contract_balance)} (owed to nobody)")
    return _Settlement(reviews, rep_table, owner_reps, payments, contract_balance)


def _run_graph_phase(demo: _Demo, training: _Training, episodes: int) -> _Graph:
    say, args, cfg, root = demo.say, demo.args, training.cfg, demo.root
    sensing = cfg.env_options.get("sensing")
    random_len = random_policy_length(TARGET["agents"], TARGET["walls"], cfg.grid, cfg.max_steps, 200,
                                      seed=args.seed + 5, sensing=sensing)
    graph: dict[str, Any] = {"skipped": True}
    graph_team: dict[str, Any] = {"skipped": True}
    if args.no_ros:
        return _Graph(random_len, graph, graph_team)
    say.step(f"6. The ROS 2 graph runs the new MEDC policy ({episodes} episodes, one process per node)")
    graph = run_graph(training.policy_paths["medc"], TARGET, cfg, episodes, args.seed, demo.out,
                      quiet=demo.quiet)
    graph["skipped"] = False
    graph["beats_random"] = bool(graph["mean_length"] < random_len)
    say.say(
        f"new policy: mean episode length {graph['mean_length']:.1f} (random moves: {random_len:.1f}); "
        f"success {graph['success_rate']:.0%}: it "
        f"{'beats' if graph['beats_random'] else 'does not beat'} random moves in the graph"
    )
    searcher = _run_searcher(demo, cfg, episodes)
    team_path = root / "models" / "team" / "A3W2.safetensors"
    if team_path.is_file():
        graph_team = _run_shipped_team(demo, team_path, episodes)
    benchmark = _run_benchmark(demo, episodes)
    return _Graph(random_len, graph, graph_team, searcher, benchmark)


def _run_searcher(demo: _Demo, cfg, episodes: int) -> dict[str, Any]:
    """The graph with the classical searcher (SEARCHER) on the new policy's episodes."""
    say, args = demo.say, demo.args
    say.say(f"the same episodes with {SEARCHER}, the classical searcher a user would field here "
            "(no learned team has beaten it in this regime yet: docs/reproduction/claims):")
    result = run_graph(SEARCHER, TARGET, cfg, episodes, args.seed, demo.out, quiet=demo.quiet,
                       sensing=cfg.env_options.get("sensing"))
    result["skipped"] = False
    result["policy"] = SEARCHER
    say.say(f"{SEARCHER}: mean episode length {result['mean_length']:.1f}; "
            f"success {result['success_rate']:.0%}")
    return result


def _run_shipped_team(demo: _Demo, team_path: Path, episodes: int) -> dict[str, Any]:
    """The graph with the shipped team (models/team) in the environment its manifest records."""
    from medc_training.bundle import read_manifest

    say, args = demo.say, demo.args
    env = read_manifest(team_path.read_bytes())["environment"]
    sensing = env.get("sensing")
    cfg = argparse.Namespace(grid=int(env["grid"]), max_steps=int(env["max_steps"]),
                             env_options={"sensing": sensing} if sensing else {})
    say.say(f"the shipped team ({team_path.relative_to(demo.root)}) in the regime it was trained for "
            f"({_regime_words(cfg)}):")
    result = run_graph(team_path, TARGET, cfg, episodes, args.seed, demo.out, quiet=demo.quiet)
    result["skipped"] = False
    result["random_episode_length"] = random_policy_length(
        TARGET["agents"], TARGET["walls"], cfg.grid, cfg.max_steps, 200, args.seed + 5, sensing=sensing)
    say.say(f"shipped team: mean episode length {result['mean_length']:.1f} (random moves there: "
            f"{result['random_episode_length']:.1f}); success {result['success_rate']:.0%}")
    return result


def _run_benchmark(demo: _Demo, episodes: int) -> dict[str, Any]:
    """The graph in the field benchmark's world: the shipped benchmark team from its launch config,
    then BENCH_SEARCHER on the same episodes (same seed, the scenario the team's manifest records)."""
    import yaml
    from medc_training.bundle import read_manifest

    say, args = demo.say, demo.args
    config = demo.root.joinpath(*BENCH_CONFIG)
    if not config.is_file():
        return {"skipped": True}
    policy = demo.root / yaml.safe_load(config.read_text())["policy"]
    env = read_manifest(policy.read_bytes())["environment"]
    name = config.relative_to(demo.root)
    say.say(f"the field benchmark's {env['grid']}x{env['grid']} world (RAD-A2C's physics, up to "
            f"{env['walls']} obstructions): the shipped benchmark team ({name}), then {BENCH_SEARCHER}, "
            "the strongest classical searcher there, on the same episodes:")
    team = launch_graph(config, episodes, args.seed, quiet=demo.quiet)
    searcher_yaml = demo.out / "launch-benchmark-searcher.yaml"
    searcher_yaml.write_text(yaml.safe_dump({
        "world": env["world"], "agents": env["agents"], "walls": env["walls"], "grid": env["grid"],
        "max_steps": env["max_steps"], "seed": args.seed, "mode": "stepped", "policy": BENCH_SEARCHER}))
    searcher = launch_graph(searcher_yaml, episodes, args.seed, quiet=demo.quiet)
    result = {"skipped": False, "config": str(name), "searcher_policy": BENCH_SEARCHER,
              "team": _graph_summary(team), "searcher": _graph_summary(searcher)}
    say.say(f"benchmark team: mean episode length {team['mean_length']:.1f}, success "
            f"{team['success_rate']:.0%}; {BENCH_SEARCHER}: {searcher['mean_length']:.1f}, success "
            f"{searcher['success_rate']:.0%} "
            f"({episodes} episodes: a glimpse; the benchmark's 960 frozen episodes are in models/README.md)")
    return result


def _summarise(demo: _Demo, allocation: _Allocation, training: _Training, settlement: _Settlement,
               graph: _Graph) -> dict[str, Any]:
    from medc_training.bundle import load_bundle

    say, out, cfg = demo.say, demo.out, training.cfg
    say.step("7. Summary and report")
    trained = load_bundle(training.policy_paths["medc"].read_bytes())
    traj = trajectory_png(trained, cfg, demo.args.seed + 7, out / "trajectory.png")
    total_s = say.finish()
    summary = {
        "ok": True,
        "quick": bool(demo.args.quick),
        "seconds": round(total_s, 1),
        "out": str(out),
        "allocations": [
            {
                "allocation": a.allocation_id,
                "model": a.model_id,
                "qos": q if math.isfinite(q) else "inf",
                "distance": a.distance,
                "price_wei": a.price_wei,
                "cid": a.cid,
            }
            for a, q in zip(allocation.allocations, allocation.qos_values)
        ],
        "qos_order_ok": allocation.qos_order_ok,
        "paid_wei": allocation.price,
        "payments": settlement.payments,
        "models_manager_balance_wei": settlement.contract_balance,
        "reviews": settlement.reviews,
        "model_reputations": settlement.model_reputations,
        "owner_reputations": settlement.owner_reputations,
        "training": {
            m: {k: r[k] for k in ("steps", "final_episode_length", "final_success_rate", "wall_s")}
            for m, r in training.results.items()
        },
        "random_policy_episode_length": graph.random_len,
        "learning_scores": training.scores,
        "medc_learned_faster_than_sparse": training.medc_faster,
        "new_policy_beats_random_in_graph": graph.graph.get("beats_random"),
        "graph": _graph_summary(graph.graph),
        "graph_searcher": _graph_summary(graph.searcher, "policy"),
        "graph_shipped_team": _graph_summary(graph.shipped_team, "random_episode_length"),
        "graph_benchmark": graph.benchmark,
        "trajectory": traj,
        "gas": dict(demo.gas),
        "timings_s": say.timings,
    }
    write_report(out, summary, cfg)
    say.say(f"report: {out / 'report.md'}")
    return summary


def _graph_summary(graph: dict, *extra: str) -> dict:
    """A graph run's figures for the summary, with the ``extra`` keys it holds."""
    keys = ("skipped", "episodes", "mean_length", "success_rate", "episode_lengths", "wall_s", *extra)
    return {k: graph[k] for k in keys if k in graph}


def run_graph(policy: Path | str, target: dict, cfg, episodes: int, seed: int, out: Path,
              quiet: bool = False, sensing: str | None = None) -> dict:
    """Run ``medc-launch`` (simulator + one agent node per agent, each its own process) for
    ``episodes`` episodes with ``policy`` (a bundle, or a classical controller by name) under
    ``sensing`` (None: the bundle's); its per-episode lines are shown live (not ``quiet``)."""
    import yaml

    launch_yaml = out / "launch.yaml"
    launch_yaml.write_text(yaml.safe_dump({
        "agents": target["agents"], "walls": target["walls"], "grid": cfg.grid, "max_steps": cfg.max_steps,
        "seed": seed, "mode": "stepped", "policy": str(policy), **({"sensing": sensing} if sensing else {}),
    }))
    return launch_graph(launch_yaml, episodes, seed, quiet=quiet)


def launch_graph(config: Path, episodes: int, seed: int, quiet: bool = False) -> dict:
    """Run ``medc-launch --config config`` with ``seed`` for ``episodes`` episodes and return its
    JSON line; its per-episode lines are shown live (not ``quiet``)."""
    cmd = [str(Path(sys.executable).parent / "medc-launch"), "--config", str(config), "--seed", str(seed),
           "--episodes", str(episodes), "--timeout", "300"]
    last_json = None
    with subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) as proc:
        assert proc.stdout is not None
        tail: list[str] = []
        for line in proc.stdout:
            line = line.rstrip()
            tail = [*tail[-29:], line]
            if line.startswith("{"):
                last_json = line
            elif line.startswith("episode ") and not quiet:
                print(f"      {line}", flush=True)
        rc = proc.wait()
    if rc != 0 or last_json is None:
        shown = "\n".join(tail)
        raise RuntimeError(f"medc-launch exited with {rc} ({' '.join(cmd)}); its last output:\n{shown}")
    return json.loads(last_json)


def write_report(out: Path, s: dict, cfg) -> None:
    """report.md: allocation, payments, reputations, learning, graph results, gas, figures."""
    lines = [
        "# MEDC demo report",
        "",
        f"Run {'(quick)' if s['quick'] else ''} in {s['seconds']:.0f} s; environment A3W2, "
        f"{_regime_words(cfg)}.",
        *_market_lines(s),
        *_learning_lines(s),
        *_graph_lines(s),
        "",
        "![one episode](trajectory.png)",
        "",
        "## Gas used",
        "",
        "| function | gas (each call) |",
        "|---|---|",
        *(f"| {fn} | {', '.join(f'{v:,}' for v in values)} |" for fn, values in s["gas"].items()),
    ]
    (out / "report.md").write_text("\n".join(lines) + "\n")
    (out / "summary.json").write_text(json.dumps(s, indent=2, default=str) + "\n")


def _market_lines(s: dict) -> list[str]:
    """The report's allocation, payment, review and reputation sections."""
    lines = [
        "",
        "## Allocation (Models Manager Contract, greedy by QoS)",
        "",
        "| allocation | model | D_m | QoS | price | CID |",
        "|---|---|---|---|---|---|",
    ]
    for a in s["allocations"]:
        q = a["qos"] if isinstance(a["qos"], str) else f"{a['qos']:.3f}"
        lines.append(
            f"| {a['allocation']} | {a['model']} | {a['distance']:.2f} | {q} | "
            f"{a['price_wei'] / ETHER:.4f} ETH | `{a['cid']}` |"
        )
    lines += [
        "",
        f"Paid {s['paid_wei'] / ETHER:.4f} ETH; after withdrawals the contract holds "
        f"{s['models_manager_balance_wei'] / ETHER:.4f} ETH.",
        "",
        "## Reviews and reputations",
        "",
        "| model | review | reputation before | after |",
        "|---|---|---|---|",
    ]
    reps = {r["model"]: r for r in s["model_reputations"]}
    for r in s["reviews"]:
        rep = reps[r["model"]]
        lines.append(f"| {r['model']} | {r['review']:.3f} | {rep['before']:.3f} | {rep['after']:.3f} |")
    lines += ["", "| owner | reputation before | after | withdrawn |", "|---|---|---|---|"]
    paid = {p["owner"]: p["withdrawn_wei"] for p in s["payments"]}
    for o in s["owner_reputations"]:
        lines.append(
            f"| {o['owner']} | {o['before']:.3f} | {o['after']:.3f} | {paid[o['owner']] / ETHER:.4f} ETH |"
        )
    return lines


def _learning_lines(s: dict) -> list[str]:
    """The report's learning section: each method's run and the learning scores."""
    lines = [
        "",
        "## Learning (same budget, same seed)",
        "",
        "| method | steps | final episode length | success | wall s |",
        "|---|---|---|---|---|",
    ]
    for m, r in s["training"].items():
        lines.append(
            f"| {m} | {r['steps']:,} | {r['final_episode_length']:.1f} | {r['final_success_rate']:.0%} | "
            f"{r['wall_s']:.0f} |"
        )
    sc = s["learning_scores"]
    lines += ["", f"Learning score (mean greedy evaluation episode length over the run, lower = faster): "
              f"MEDC {sc['medc']:.2f}, sparse {sc['sparse']:.2f}; MEDC learned "
              f"{'faster' if s['medc_learned_faster_than_sparse'] else 'no faster'} than sparse on this seed "
              f"({ONE_SEED})."]
    return [*lines, "", "![learning curves](learning_curves.png)"]


def _graph_lines(s: dict) -> list[str]:
    """The report's ROS 2 graph section: the new policy's episodes, the searcher's on the same ones and
    the shipped team's."""
    lines = ["", "## The ROS 2 graph", ""]
    g = s["graph"]
    if g.get("skipped"):
        lines.append("Skipped (--no-ros).")
    else:
        lines.append(
            f"{g['episodes']} episodes: lengths {g['episode_lengths']}, mean {g['mean_length']:.1f}, "
            f"success {g['success_rate']:.0%}; a random policy averages "
            f"{s['random_policy_episode_length']:.1f} steps: the new policy "
            f"{'beats' if s['new_policy_beats_random_in_graph'] else 'does not beat'} random moves."
        )
    r = s.get("graph_searcher") or {}
    if not r.get("skipped", True):
        lines += ["", f"The same episodes with {r['policy']}, the classical searcher a user would field "
                  f"here: lengths {r['episode_lengths']}, mean {r['mean_length']:.1f}, success "
                  f"{r['success_rate']:.0%}."]
    t = s.get("graph_shipped_team") or {}
    if not t.get("skipped", True):
        lines += ["", f"The shipped team (models/team) in the regime it was trained for: {t['episodes']} "
                  f"episodes, lengths {t['episode_lengths']}, mean {t['mean_length']:.1f}, success "
                  f"{t['success_rate']:.0%}; random moves average {t['random_episode_length']:.1f} steps "
                  "there."]
    b = s.get("graph_benchmark") or {}
    if not b.get("skipped", True):
        team, searcher = b["team"], b["searcher"]
        lines += ["", f"The field benchmark's world, the shipped benchmark team (`{b['config']}`): lengths "
                  f"{team['episode_lengths']}, mean {team['mean_length']:.1f}, success "
                  f"{team['success_rate']:.0%}; {b['searcher_policy']} on the same episodes: lengths "
                  f"{searcher['episode_lengths']}, mean {searcher['mean_length']:.1f}, success "
                  f"{searcher['success_rate']:.0%} (on the benchmark's 960 frozen episodes: 11.58 moves "
                  "against 14.20, models/README.md)."]
    return lines


def main(argv: list[str] | None = None) -> int:
    from medc_training.console import QUIET_HELP, HelpFormatter, epilog

    p = argparse.ArgumentParser(prog="medc-demo", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter, epilog=epilog(__doc__))
    p.add_argument("--quick", action="store_true", help="small budgets (about 1.5 minutes after set-up)")
    p.add_argument("--out", default="demo-out", help="output folder (default demo-out)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--steps", type=int, help="training steps per method (default 204,800; quick 40,960)")
    p.add_argument("--episodes", type=int, help="episodes the ROS graph runs (default 10; quick 5)")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    p.add_argument("--no-ros", action="store_true", help="skip step 6 (the ROS 2 graph)")
    p.add_argument("--quiet", action="store_true", help=QUIET_HELP)
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars, the step lines stay (--quiet drops both)")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    try:
        summary = run(args)
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        print(f"medc-demo: error: {exc}", file=sys.stderr)
        print(json.dumps({"ok": False, "error": str(exc)}))
        return 1
    print(json.dumps(summary, default=str))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
