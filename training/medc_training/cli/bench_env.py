"""`medc-bench env`: agent-steps per second of the target-localization core, per sensing preset.

By default two scenarios, each with its throughput target (B = 256, A3W2, one torch thread,
``copy_obs=False``):

- ``paper-simple`` on the paper's 30×30 grid: the default observation, target ≥ 100,000;
- ``realistic`` on 20×20: the default observation, target ≥ 50,000.

Each scenario is also measured with the ``maps`` observation (the paper's 5 absolute maps, no
source estimate) and with the observation on the reference estimator (``reference``: the estimator
path the fused one replaced, :data:`~medc_training.envs.tl_observation.ESTIMATOR_PATHS`) in the
same run, interleaved round by round with the default, and every figure is printed as a ratio to
them too (A/B: fused / reference): absolute figures on a shared machine move with the other jobs'
load, the ratios much less. Where the estimator's native kernel is loaded
(:mod:`~medc_training.envs.tl_native`) the fused path is also measured on torch alone (``torch``:
the A/B of the kernel). ``--no-reference`` skips the reference and the torch twin. ``--grid``, ``--sensing``,
``--walls``, ``--agents`` or ``--observation`` measure one custom scenario instead;
``--one-by-one-steps N`` adds B separate ``make_env`` ParallelEnvs stepped in turn through the
PettingZoo API (the batched / one-by-one ratio).

Every path is stepped with random valid moves sampled from the mask each step (included in the
time), observations built every step, auto-resets included. Each measurement is time-boxed: a
warm-up (``--warmup`` steps and at least ``--warmup-seconds``), then ``--rounds`` interleaved
rounds of ``--seconds / --rounds`` each (at least one step per round), medians reported (the ratio
is the median of the per-round ratios). Agent-steps = environment steps × agents. Torch runs on
one intra-op thread by default (``--threads``): the per-step tensors are small, and on a shared
2-core machine a second thread costs more in synchronisation than it gains. Last line: one JSON
object with every figure.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from medc_training.envs import make_batched, make_env, tl_native
from medc_training.envs.names import TARGET_LOCALIZATION
from medc_training.envs.tl_observation import DEFAULT_OBSERVATION, estimator_path

#: The measured scenarios: (sensing preset, grid, target agent-steps/s with the default observation).
SCENARIOS: tuple[tuple[str, int, int], ...] = (("paper-simple", 30, 100_000), ("realistic", 20, 50_000))
BASELINE_OBSERVATION = "maps"


class _Batched:
    """A batched core stepped with random valid moves sampled from its mask."""

    def __init__(self, args: argparse.Namespace, sensing: str, grid: int, observation: str,
                 copy_obs: bool = False, path: str = "fused", native: bool = True) -> None:
        start = time.perf_counter()
        self.native = native
        with estimator_path(path):
            self.env = self._make(args, sensing, grid, observation, copy_obs)
        self.gen = torch.Generator(device=self.env.device).manual_seed(args.seed)
        _, self.mask = self.env.reset()
        self.setup_s = time.perf_counter() - start
        self.cuda = self.env.device.type == "cuda"

    @staticmethod
    def _make(args: argparse.Namespace, sensing: str, grid: int, observation: str, copy_obs: bool):
        return make_batched(TARGET_LOCALIZATION, num_envs=args.num_envs, device=args.device, seed=args.seed,
                            agents=args.agents, walls=args.walls, grid=grid, max_steps=args.max_steps,
                            observation=observation, sensing=sensing, copy_obs=copy_obs)

    def run(self, seconds: float, min_steps: int = 1, max_steps: int = 0) -> tuple[float, int]:
        """Step for ``seconds`` (at least ``min_steps``, at most ``max_steps`` when > 0):
        (agent-steps/s, steps); without the native kernel when this path was made without it."""
        if not self.native:
            with tl_native.turned_off():
                return self._run(seconds, min_steps, max_steps)
        return self._run(seconds, min_steps, max_steps)

    def _run(self, seconds: float, min_steps: int, max_steps: int) -> tuple[float, int]:
        b, n, a = self.mask.shape
        if self.cuda:
            torch.cuda.synchronize()
        start = time.perf_counter()
        steps = 0
        while True:
            actions = torch.multinomial(self.mask.view(-1, a).float(), 1, generator=self.gen).view(b, n)
            self.mask = self.env.step(actions).mask
            steps += 1
            if self.cuda:
                torch.cuda.synchronize()
            elapsed = time.perf_counter() - start
            if steps >= min_steps and (elapsed >= seconds or 0 < max_steps <= steps):
                return steps * b * n / elapsed, steps


class _OneByOne:
    """B separate ParallelEnvs stepped in turn with random valid moves from their masks."""

    def __init__(self, args: argparse.Namespace, sensing: str, grid: int, observation: str) -> None:
        start = time.perf_counter()
        self.envs = [
            make_env(TARGET_LOCALIZATION, seed=args.seed + i, agents=args.agents, walls=args.walls,
                     grid=grid, max_steps=args.max_steps, observation=observation, sensing=sensing)
            for i in range(args.num_envs)
        ]
        self.rng = np.random.default_rng(args.seed)
        self.obs = [e.reset()[0] for e in self.envs]
        self.setup_s = time.perf_counter() - start

    def run(self, steps: int) -> tuple[float, int]:
        """Step every env ``steps`` times: (agent-steps/s, steps)."""
        agent_steps = 0
        start = time.perf_counter()
        for _ in range(steps):
            for i, env in enumerate(self.envs):
                acts = {}
                for agent in env.agents:
                    allowed = np.flatnonzero(self.obs[i][agent]["action_mask"])
                    acts[agent] = int(self.rng.choice(allowed))
                self.obs[i], *_ = env.step(acts)
                agent_steps += len(acts)
                if not env.agents:
                    self.obs[i] = env.reset()[0]
        return agent_steps / (time.perf_counter() - start), steps


def _print_summary(args: argparse.Namespace, result: dict, labels: dict[str, str], steps: dict[str, int],
                   rates: tuple[float, float, float], target: int | None) -> None:
    """The summary lines of :func:`measure` for the paths timed (``labels``'s keys)."""
    rate, baseline, ratio = rates
    observation = args.observation
    counts = ", ".join(f"{steps[k]} {labels[k]}" for k in labels)
    print(f"  median of {args.rounds} rounds (timed steps: {counts}):")
    line = f"  {observation:<28} {rate:12,.0f} agent-steps/s ({result['ms_per_step']:.1f} ms/step)"
    if target is not None:
        verdict = "met" if result["meets_target"] else f"NOT met ({rate / target:.1%} of it)"
        line += f", target >= {target:,}: {verdict}"
    print(line)
    if "reference" in labels:
        print(f"  {labels['reference']:<28} {result['reference_agent_steps_per_s']:12,} agent-steps/s "
              f"({result['reference_ms_per_step']:.1f} ms/step)")
        print(f"  A/B fused / reference estimator: {result['speedup_over_reference']:.3f}x")
    if "torch" in labels:
        print(f"  {labels['torch']:<28} {result['torch_agent_steps_per_s']:12,} agent-steps/s "
              f"({result['torch_ms_per_step']:.1f} ms/step)")
        print(f"  A/B native kernel / torch fused path: {result['speedup_kernel_over_torch']:.3f}x")
    print(f"  {BASELINE_OBSERVATION:<28} {baseline:12,.0f} agent-steps/s "
          f"({result['baseline_ms_per_step']:.1f} ms/step)")
    print(f"  ratio {observation} / {BASELINE_OBSERVATION}: {ratio:.4f}x")


def _rounds(args: argparse.Namespace, paths: dict, labels: dict, one) -> tuple[dict, dict]:
    """Interleaved timed rounds of every path (and one by one when asked), a line printed per round:
    ({key: rate or ratio per round}, {path: steps timed})."""
    per_round = args.seconds / args.rounds
    keys = ("default", "reference", "torch", "baseline", "one", "ratio", "ratio_reference", "ratio_torch",
            "ratio_one")
    rounds: dict[str, list[float]] = {k: [] for k in keys}
    steps = {"default": 0, "reference": 0, "torch": 0, "baseline": 0, "one": 0}
    for r in range(args.rounds):
        parts = []
        for key, path in paths.items():
            rate, k = path.run(per_round, max_steps=args.steps)
            rounds[key].append(rate)
            steps[key] += k
            parts.append(f"{labels[key]} {rate:,.0f}")
        if "reference" in paths:
            rounds["ratio_reference"].append(rounds["default"][-1] / rounds["reference"][-1])
            parts.append(f"fused / reference {rounds['ratio_reference'][-1]:.3f}x")
        if "torch" in paths:
            rounds["ratio_torch"].append(rounds["default"][-1] / rounds["torch"][-1])
            parts.append(f"kernel / torch {rounds['ratio_torch'][-1]:.3f}x")
        if "baseline" in paths:
            rounds["ratio"].append(rounds["default"][-1] / rounds["baseline"][-1])
            parts.append(f"ratio to maps {rounds['ratio'][-1]:.4f}x")
        if one is not None:
            rate, k = one.run(args.one_by_one_steps)
            rounds["one"].append(rate)
            steps["one"] += k
            rounds["ratio_one"].append(rounds["default"][-1] / rate)
            parts.append(f"one by one {rate:,.0f} (batched / one by one {rounds['ratio_one'][-1]:.1f}x)")
        print(f"  round {r + 1} (agent-steps/s): " + ", ".join(parts))
    return rounds, steps


def measure(args: argparse.Namespace, sensing: str, grid: int, target: int | None) -> dict:
    """One scenario: ``args.observation`` on the fused estimator, on the reference estimator (unless
    ``args.no_reference``) and the maps baseline (plus one by one when asked), interleaved rounds,
    medians. Prints a line per round and a summary; returns the figures."""
    observation = args.observation
    print(f"\n{sensing}, {grid}x{grid}, A{args.agents}W{args.walls}, B={args.num_envs}, "
          f"max_steps {args.max_steps}: {observation} vs {BASELINE_OBSERVATION}"
          + ("" if args.no_reference else f", and {observation} on the reference estimator"))
    paths = {"default": _Batched(args, sensing, grid, observation)}
    labels = {"default": observation, "reference": f"{observation} (reference)",
              "torch": f"{observation} (fused, torch)", "baseline": BASELINE_OBSERVATION}
    if not args.no_reference:
        paths["reference"] = _Batched(args, sensing, grid, observation, path="reference")
    if not args.no_reference and tl_native.usable():
        paths["torch"] = _Batched(args, sensing, grid, observation, native=False)
    if observation != BASELINE_OBSERVATION:
        paths["baseline"] = _Batched(args, sensing, grid, BASELINE_OBSERVATION)
    one = _OneByOne(args, sensing, grid, observation) if args.one_by_one_steps > 0 else None
    for path in paths.values():  # warm-up: allocations, first-call overheads, the layout pool
        path.run(args.warmup_seconds, min_steps=max(1, args.warmup))
    if one is not None:
        one.run(1)
    rounds, steps = _rounds(args, paths, labels, one)

    def median(key: str) -> float | None:
        return float(np.median(rounds[key])) if rounds[key] else None

    def ms(rate: float) -> float:
        return round(1000.0 * args.num_envs * args.agents / rate, 3)

    rate = median("default")
    baseline = median("baseline") if "baseline" in paths else rate
    ratio = median("ratio") if "baseline" in paths else 1.0
    result = {
        "sensing": sensing, "grid": grid, "agents": args.agents, "walls": args.walls,
        "max_steps": args.max_steps, "num_envs": args.num_envs, "observation": observation,
        "baseline_observation": BASELINE_OBSERVATION,
        "agent_steps_per_s": round(rate),
        "baseline_agent_steps_per_s": round(baseline),
        "ratio_to_baseline": round(ratio, 4),
        "target_agent_steps_per_s": target,
        "meets_target": None if target is None else rate >= target,
        "fraction_of_target": None if target is None else round(rate / target, 4),
        "timed_steps": steps["default"], "baseline_timed_steps": steps["baseline"],
        "setup_s": round(paths["default"].setup_s, 3),
        "ms_per_step": ms(rate),
        "baseline_ms_per_step": ms(baseline),
    }
    if "reference" in paths:
        reference = median("reference")
        result.update(reference_agent_steps_per_s=round(reference), reference_ms_per_step=ms(reference),
                      reference_timed_steps=steps["reference"],
                      speedup_over_reference=round(median("ratio_reference"), 3))
    if "torch" in paths:
        torch_rate = median("torch")
        result.update(torch_agent_steps_per_s=round(torch_rate), torch_ms_per_step=ms(torch_rate),
                      torch_timed_steps=steps["torch"],
                      speedup_kernel_over_torch=round(median("ratio_torch"), 3))
    _print_summary(args, result, {k: labels[k] for k in paths}, steps, (rate, baseline, ratio), target)
    if one is not None:
        one_rate, ratio_one = median("one"), median("ratio_one")
        result.update(one_by_one_agent_steps_per_s=round(one_rate), ratio_to_one_by_one=round(ratio_one, 1),
                      one_by_one_setup_s=round(one.setup_s, 3))
        print(f"  one by one through the ParallelEnv API: {one_rate:,.0f} agent-steps/s; "
              f"batched / one by one: {ratio_one:.1f}x")
    return result


def main(argv: list[str] | None = None) -> int:
    from ..console import HelpFormatter

    p = argparse.ArgumentParser(prog="medc-bench env", description=__doc__.split("\n\n")[0],
                                formatter_class=HelpFormatter)
    p.add_argument("--num-envs", type=int, default=256)
    p.add_argument("--agents", type=int, default=3)
    p.add_argument("--walls", type=int, default=2)
    p.add_argument("--grid", type=int, default=None,
                   help="a custom scenario on this grid (default: the two target scenarios)")
    p.add_argument("--sensing", choices=[s for s, _, _ in SCENARIOS], default=None,
                   help="a custom scenario with this sensing preset (its target grid unless --grid)")
    p.add_argument("--observation", default=DEFAULT_OBSERVATION,
                   help=f"the observation measured against {BASELINE_OBSERVATION!r} (default: %(default)s)")
    p.add_argument("--max-steps", type=int, default=100, help="episode length limit")
    p.add_argument("--seconds", type=float, default=4.0,
                   help="timed seconds per path and scenario, split over the rounds (each round >= 1 step)")
    p.add_argument("--rounds", type=int, default=10, help="interleaved measurement rounds (medians reported)")
    p.add_argument("--warmup", type=int, default=1, help="untimed steps of each path first")
    p.add_argument("--warmup-seconds", type=float, default=0.5, help="... and at least this long")
    p.add_argument("--steps", type=int, default=0, help="at most this many timed steps per round (0: no cap)")
    p.add_argument("--one-by-one-steps", type=int, default=0,
                   help="also step B ParallelEnvs one by one, this many steps each per round (0: skip)")
    p.add_argument("--no-reference", action="store_true",
                   help="skip the reference estimator (the A/B against the path the fused one replaced)")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads")
    p.add_argument("--device", default="cpu")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.rounds < 1 or args.seconds < 0:
        p.error("--rounds must be >= 1 and --seconds >= 0")
    torch.set_num_threads(args.threads)
    custom = (args.grid is not None or args.sensing is not None or args.walls != 2 or args.agents != 3
              or args.observation != DEFAULT_OBSERVATION)
    if custom:
        sensing = args.sensing or SCENARIOS[0][0]
        target_grid, target = next((g, t) for s, g, t in SCENARIOS if s == sensing)
        grid = target_grid if args.grid is None else args.grid
        standard = (grid == target_grid and args.walls == 2 and args.agents == 3
                    and args.observation == DEFAULT_OBSERVATION and args.num_envs == 256)
        scenarios = [(sensing, grid, target if standard else None)]
    else:  # the targets are stated for B = 256
        scenarios = [(s, g, t if args.num_envs == 256 else None) for s, g, t in SCENARIOS]
    load = " ".join(f"{x:.2f}" for x in loadavg())
    print(f"medc-bench env: target localization, B={args.num_envs}, device={args.device}, "
          f"torch threads={args.threads}, load average {load}; estimator: {tl_native.status()}")
    start = time.perf_counter()
    results = {f"{s}_{g}x{g}": measure(args, s, g, t) for s, g, t in scenarios}
    wall = time.perf_counter() - start
    print(f"\nsummary (agent-steps/s, {args.observation} and as a ratio to {BASELINE_OBSERVATION}; "
          f"{wall:.1f} s in all):")
    for name, r in results.items():
        target = "" if r["target_agent_steps_per_s"] is None else (
            f", target {r['target_agent_steps_per_s']:,}: {'met' if r['meets_target'] else 'NOT met'}")
        ab = "" if "speedup_over_reference" not in r else (
            f", {r['speedup_over_reference']:.3f}x the reference estimator at "
            f"{r['reference_agent_steps_per_s']:,}")
        if "speedup_kernel_over_torch" in r:
            ab += f", {r['speedup_kernel_over_torch']:.3f}x the torch fused path"
        print(f"  {name:<20} {r['agent_steps_per_s']:>10,} ({r['ratio_to_baseline']:.4f}x "
              f"{BASELINE_OBSERVATION} at {r['baseline_agent_steps_per_s']:,}{ab}){target}")
    print(json.dumps({"scenarios": results, "device": args.device, "threads": args.threads,
                      "native_kernel": tl_native.usable(),
                      "seconds_per_path": args.seconds, "rounds": args.rounds, "load_average": loadavg(),
                      "wall_s": round(wall, 1)}))
    return 0


def loadavg() -> list[float]:
    """The machine's load averages over 1, 5 and 15 minutes (empty where the system has none)."""
    try:
        import os

        return [round(x, 2) for x in os.getloadavg()]
    except (OSError, AttributeError):
        return []


if __name__ == "__main__":
    raise SystemExit(main())
