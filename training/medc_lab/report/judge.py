"""Judging: the learnability gate of an environment, the verdict of each of the paper's claims,
and the counts of the verdicts; every band and test from :mod:`medc_training.stats`."""

from __future__ import annotations

import json
import math
from collections.abc import Collection, Sequence
from pathlib import Path

from medc_training.stats import compare, learning_score, mean_ci

from ..catalogue import Scope
from .finder import seed_dirs
from .reference_play import random_play_length

#: Seeds the learnability gate needs before it can pass.
GATE_MIN_SEEDS = 3


def learnability_gate(out: Path, sparse_run: str, min_seeds: int = GATE_MIN_SEEDS,
                      random_episodes: int | None = None, seeds: Collection[int] | None = None) -> dict:
    """Did MDRL-sparse learn in ``sparse_run``'s environment? Per seed, its final evaluation episode
    length (mean of the last three evaluations) minus random play's on the same evaluation
    episodes (or on ``random_episodes`` fixed episodes of the same seed); passed when >= ``min_seeds``
    seeds ran and the 95% CI of the mean difference lies entirely below 0 (``seeds``: only those
    seeds count). Returns {"passed", "n", "sparse", "random", "diff", "half", "text"}."""
    from medc_training.metrics import read_metrics

    finals, randoms = [], []
    for seed_dir in seed_dirs(out, sparse_run, seeds):
        summary = json.loads((seed_dir / "summary.json").read_text())
        rows = read_metrics(seed_dir / "metrics.csv")
        finals.append(sum(r["episode_length"] for r in rows[-3:]) / len(rows[-3:]))
        randoms.append(random_play_length(out, summary["config"], random_episodes))
    diffs = [f - r for f, r in zip(finals, randoms)]
    m, half = mean_ci(diffs)
    passed = len(diffs) >= min_seeds and m + half < 0
    ms, _ = mean_ci(finals)
    mr, _ = mean_ci(randoms)
    where = (f"{random_episodes} fixed episodes of each seed" if random_episodes
             else "the same evaluation episodes")
    text = (f"MDRL-sparse final episode length {ms:.2f} vs random play {mr:.2f} on {where}: difference "
            f"{m:+.2f} ± {half:.2f} (95% CI, n = {len(diffs)} seeds)")
    return {"passed": passed, "n": len(diffs), "sparse": ms, "random": mr, "diff": m, "half": half,
            "text": text}


def verdict(better: list[float], worse: list[float], underpowered: float | None = None) -> str:
    """How the paper's claim "``better`` learns faster than ``worse``" fared (lower learning
    score is better): held / contradicted when the 95% CI of the difference excludes 0, else
    not resolved, saying which way the means lean (and "under-powered" when the CI's half-width
    exceeds ``underpowered``)."""
    if not better or not worse:
        return "not run"
    c = compare(better, worse)
    if c["diff"] == 0:
        return "no difference"
    if c["diff"] + c["half"] < 0:
        return "held"
    if c["diff"] - c["half"] > 0:
        return "contradicted (CI excludes 0 the other way)"
    weak = ", under-powered" if underpowered is not None and c["half"] > underpowered else ""
    if c["diff"] < 0:
        return f"not resolved (means lean the paper's way; CI includes 0{weak})"
    return f"not resolved (means lean against the paper; CI includes 0{weak})"


class Judge:
    """The verdicts of one report: the learning scores of the series read so far, the learnability
    gate of each environment (computed once), and every claim judged, in order, with what its
    analysis after the protocol needs (:mod:`.posthoc`)."""

    def __init__(self, out: Path, scope: Scope) -> None:
        self.out, self.scope = out, scope
        #: Per series key, the learning score of each seed read.
        self.scores: dict[str, list[float]] = {}
        #: Per series key, its learning score by seed (the seed its config names), as last read.
        self.seed_scores: dict[str, dict[int, float]] = {}
        #: Learnability gate of each environment, by (its MDRL-sparse run name, the seeds it needs,
        #: the seeds it reads or None for all).
        self.gates: dict[tuple, dict] = {}
        #: The verdict word of every claim written, in order (for the counts).
        self.verdicts: list[str] = []
        #: Every claim written, in order: its text, the verdict word, the margin (None: "beats") and
        #: both sides' scores by seed as the claim read them.
        self.claim_records: list[dict] = []

    def record(self, key: str, curves: Sequence[Sequence[float]], summaries: Sequence[dict]) -> None:
        """Keep the learning scores of series ``key`` (one curve and summary.json per seed)."""
        self.scores[key] = [learning_score(c) for c in curves]
        self.seed_scores[key] = {int(s["config"]["seed"]): score
                                 for s, score in zip(summaries, self.scores[key], strict=True)}

    def gate_result(self, sparse_run: str, min_seeds: int | None = None,
                    seeds: tuple[int, ...] | None = None) -> dict:
        """:func:`learnability_gate` of ``sparse_run`` (needing ``min_seeds``, None: the scope's;
        reading ``seeds``, None: all), computed once per report."""
        need = min_seeds or self.scope.gate_min_seeds
        key = (sparse_run, need, seeds)
        if key not in self.gates:
            self.gates[key] = learnability_gate(self.out, sparse_run, need, self.scope.gate_random_episodes,
                                                seeds)
        return self.gates[key]

    def gate(self, sparse_run: str, min_seeds: int | None = None,
             seeds: tuple[int, ...] | None = None) -> str:
        """The gate line for ``sparse_run``'s environment; claims made with ``gate=sparse_run``
        are "not testable" unless it passed."""
        g = self.gate_result(sparse_run, min_seeds, seeds)
        if g["n"] == 0:
            return "- **Learnability gate** — not run"
        need = min_seeds or self.scope.gate_min_seeds
        if g["passed"]:
            word = "passed"
        elif g["n"] < need:
            word = (f"NOT passed yet (needs >= {need} seeds, {g['n']} ran): this environment's claims "
                    "are not testable until the rest of MDRL-sparse's seeds have run")
        else:
            word = (f"NOT passed (needs >= {need} seeds and a CI below 0): the scale is too small for "
                    "MDRL-sparse to learn here, so this environment's claims are not testable")
        return f"- **Learnability gate** ({sparse_run}) — {word}: {g['text']}"

    def _untestable(self, gate: str | None, min_seeds: int | None = None,
                    seeds: tuple[int, ...] | None = None) -> str | None:
        if gate is None:
            return None
        g = self.gate_result(gate, min_seeds, seeds)
        if g["passed"]:
            return None
        return (f"not testable (MDRL-sparse did not pass the learnability gate: difference to random "
                f"play {g['diff']:+.2f} ± {g['half']:.2f}, n = {g['n']})")

    def _incomplete(self, a: list, b: list) -> str | None:
        """"incomplete ..." when a side of a claim (its seeds' scores ``a``, ``b``) has fewer seeds
        than the scope's ``claim_min_seeds`` (but at least one: none is "not run")."""
        need = self.scope.claim_min_seeds
        if need is None or not a or not b or (len(a) >= need and len(b) >= need):
            return None
        return f"incomplete ({len(a)} and {len(b)} of {need} seeds ran; no verdict yet)"

    def claim(self, text: str, better: str, worse: str, gate: str | None = None, *,
              min_seeds: int | None = None, seeds: tuple[int, ...] | None = None) -> str:
        """A claim's verdict line; "not testable" unless ``gate``'s learnability gate passed (with
        ``min_seeds`` and ``seeds`` as in :meth:`gate_result`)."""
        a, b = self.scores.get(better, []), self.scores.get(worse, [])
        c = compare(a, b) if a and b else {"diff": math.nan, "half": math.nan}
        blocked = self._untestable(gate, min_seeds, seeds) if a and b else None
        word = blocked or self._incomplete(a, b) or verdict(a, b, self.scope.underpowered)
        self.verdicts.append(word)
        self._record(text, word, better, worse, None)
        return (f"- **{text}** — {word}: difference of learning scores "
                f"{c['diff']:+.2f} ± {c['half']:.2f} (negative = first is better; n = {len(a)} vs {len(b)})")

    def claim_no_worse(self, text: str, faulty: str, sparse: str, margin: float,
                       gate: str | None = None, *, min_seeds: int | None = None,
                       seeds: tuple[int, ...] | None = None) -> str:
        a, b = self.scores.get(faulty, []), self.scores.get(sparse, [])
        if not a or not b:
            self.verdicts.append("not run")  # counted with the others, as claim() counts it
            return f"- **{text}** — not run"
        c = compare(a, b)
        ok = c["diff"] - c["half"] <= margin
        word = "held" if c["diff"] <= margin and ok else ("inconclusive" if ok else "did not hold")
        word = self._untestable(gate, min_seeds, seeds) or self._incomplete(a, b) or word
        self.verdicts.append(word)
        self._record(text, word, faulty, sparse, margin)
        return (f"- **{text}** — {word}: {c['diff']:+.2f} ± {c['half']:.2f} episode-length steps vs sparse "
                f"(allowed margin {margin:+.1f}; n = {len(a)} vs {len(b)})")

    def _record(self, text: str, word: str, first: str, second: str, margin: float | None) -> None:
        self.claim_records.append({"text": text, "word": word, "margin": margin,
                                   "first": dict(self.seed_scores.get(first, {})),
                                   "second": dict(self.seed_scores.get(second, {}))})

    def verdict_counts(self) -> str:
        """One line counting the claims by verdict (held, contradicted, not resolved, ...)."""
        kinds = ("held", "contradicted", "did not hold", "inconclusive", "not resolved", "not testable",
                 "no difference", "incomplete", "not run")
        counts = {k: sum(v.startswith(k) for v in self.verdicts) for k in kinds}
        return (f"{len(self.verdicts)} claims: " + ", ".join(f"{n} {k}" for k, n in counts.items() if n)
                if self.verdicts else "no claims")
