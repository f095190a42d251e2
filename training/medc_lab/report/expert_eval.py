"""The experts' own quality, beside the classical controllers: each target-localization expert
bundle played greedily on fixed episodes of its own environment and of the team the runs train
(A3W2), with the seed and episode count of the reference lines (:mod:`.references`), so a reader
can set an expert against the controllers a user would pick instead.

Results are cached in ``OUT/expert_eval.json`` by bundle content (sha256) and environment, so a
report rebuild plays nothing new and a re-cloned expert is played again.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from medc_training.stats import mean_ci

#: The fixed episodes of the claims protocol's reference lines (python -m medc_lab.cli.regimes --episodes 512
#: --eval-seed 20261204).
EPISODES = 512
EVAL_SEED = 20261204
#: The team every run trains: 3 agents, 2 walls.
TEAM = (3, 2)


def _play(path: Path, agents: int, walls: int, base: dict, episodes: int, seed: int) -> dict:
    """Greedy play of the bundle at ``path`` with ``agents`` agents among ``walls`` walls."""
    from medc_training.bundle import load_bundle, manifest_observation
    from medc_training.envs import make_batched
    from medc_training.evaluate import net_policy, play_episodes

    bundle = load_bundle(path)
    env = make_batched(bundle.manifest["application"], num_envs=episodes, seed=seed, agents=agents,
                       walls=walls, grid=base["grid"], max_steps=base["max_steps"], copy_obs=False,
                       observation=manifest_observation(bundle.manifest), **base.get("env_options", {}))
    played = play_episodes(env, net_policy(bundle.net), episodes=episodes, seed=seed, greedy=True)
    return {"lengths": [float(x) for x in played.lengths],
            "successes": [float(bool(x)) for x in played.successes]}


def evaluate_experts(out: Path, models: Path, base: dict, episodes: int = EPISODES,
                     seed: int = EVAL_SEED) -> dict[str, dict]:
    """{"NAME own" / "NAME A3W2": {"agents", "walls", "length", "length_ci", "success"}} for every
    target-localization bundle in ``models/experts``; plays what the cache lacks."""
    import hashlib

    from medc_training.bundle import BundleError, read_manifest
    from medc_training.envs import application

    cache_path = out / "expert_eval.json"
    cache = json.loads(cache_path.read_text()) if cache_path.exists() else {}
    results = {}
    for path in sorted((models / "experts").glob("*.safetensors")):
        try:
            manifest = read_manifest(path)
            env = manifest["environment"]
            searches = application(manifest["application"]).has_estimate
        except (BundleError, KeyError, ValueError) as exc:
            print(f"[expert-eval] {path.name}: not evaluated ({exc})", file=sys.stderr)
            continue
        if not searches:
            continue  # not a bundle of a source search
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
        own = (int(env["agents"]), int(env.get("walls", 0)))
        for where, (agents, walls) in (("own", own), (f"A{TEAM[0]}W{TEAM[1]}", TEAM)):
            key = f"{path.stem}|{digest}|A{agents}W{walls}|{episodes}|{seed}"
            if key not in cache:
                print(f"[expert-eval] {path.stem} on A{agents}W{walls} ...", file=sys.stderr, flush=True)
                cache[key] = _play(path, agents, walls, base, episodes, seed)
                cache_path.write_text(json.dumps(cache) + "\n")
            length, half = mean_ci(cache[key]["lengths"])
            success, _ = mean_ci(cache[key]["successes"])
            results[f"{path.stem} {where}"] = {"agents": agents, "walls": walls, "length": length,
                                              "length_ci": half, "success": success}
    return results


def expert_eval_table(results: dict[str, dict], refs: dict[str, dict]) -> str:
    """Markdown: each expert on its own environment and on A3W2, then the reference policies (on A3W2)."""
    if not results:
        return ""
    rows = ["| policy | played as | mean episode length ± 95% CI | found |", "|---|---|---|---|"]
    def row(policy: str, played_as: str, r: dict) -> str:
        return f"| {policy} | {played_as} | {r['length']:.1f} ± {r['length_ci']:.1f} | {r['success']:.0%} |"

    for name, r in results.items():
        bundle, where = name.rsplit(" ", 1)
        own = f"own environment (A{r['agents']}W{r['walls']})"
        rows.append(row(f"expert {bundle}", own if where == "own" else f"the team ({where})", r))
    for name, r in sorted(refs.items(), key=lambda kv: kv[1]["length"]):
        rows.append(row(name, f"the team (A{TEAM[0]}W{TEAM[1]})", r))
    return "\n".join(rows)
