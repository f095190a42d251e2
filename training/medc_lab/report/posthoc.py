"""The analysis a report adds after its protocol's verdicts, on the same runs, labelled with its
date; the verdicts themselves stay as the protocol judged them.

The runs of a seed share that seed (its fixed evaluation episodes and its seeding), so each claim
is also compared **paired by seed** (:func:`medc_training.stats.paired`). For every directional
claim ("X beats Y") with a verdict, under the protocol's test (Welch, df = min(n) - 1) and the
paired one (df = n - 1): the difference with its 95% CI, the two-sided p-value, the p-value
Holm-adjusted across the report's directional claims (:func:`medc_training.stats.holm`), the
power at the observed difference and the difference detected with 80% power, both from the
noncentral t of that test. A non-inferiority claim ("at worst ``margin`` behind") is judged by its
CI's upper bound (:func:`medc_training.stats.non_inferiority`). The steps to MDRL-sparse's final
level count a seed that never reaches it at its budget (:func:`medc_training.stats.censored_mean`).
The section closes with every claim whose reading changes under pairing, power or Holm.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from medc_training.stats import (
    ALPHA,
    censored_mean,
    detectable_delta,
    holm,
    non_inferiority,
    paired,
    t_power,
    welch,
)

from .references import final_level, steps_to_level

#: Verdict words of a claim that was judged (the others: not testable, incomplete, not run).
JUDGED = ("held", "contradicted", "not resolved", "no difference", "did not hold", "inconclusive")
#: The power below which a test is called under-powered for a difference.
POWER = 0.8


def base_word(word: str) -> str:
    """A verdict's word without its note ("not resolved (means lean ...)" -> "not resolved")."""
    return next((w for w in JUDGED if word.startswith(w)), word)


def _pvalue(p: float) -> str:
    if math.isnan(p):
        return "–"
    return "< 0.001" if p < 0.001 else f"{p:.3f}"


def _reading(diff: float, p: float) -> str:
    """"held" / "contradicted" when ``p`` < ALPHA in / against the claim's direction (lower =
    better), else "not resolved"."""
    if math.isnan(p) or p >= ALPHA:
        return "not resolved"
    return "held" if diff < 0 else "contradicted"


def _ci_reading(diff: float, half: float) -> str:
    """The protocol's rule on a CI: held / contradicted when it excludes 0, else not resolved."""
    if diff + half < 0:
        return "held"
    if diff - half > 0:
        return "contradicted"
    return "no difference" if diff == 0 else "not resolved"


class _Detectable:
    """The test's detectable difference in standard errors, by df (computed once each)."""

    def __init__(self) -> None:
        self.by_df: dict[int, float] = {}

    def __call__(self, df: int) -> float:
        if df not in self.by_df:
            self.by_df[df] = detectable_delta(df, POWER)
        return self.by_df[df]


def _power(test: dict, df: int, detectable: _Detectable) -> tuple[float, float]:
    """(power at the observed difference, the difference detected with 80% power) of ``test``
    (:func:`welch` or :func:`paired`'s dict) on ``df`` degrees of freedom."""
    se = test["se"]
    if df < 1 or not math.isfinite(se) or se <= 0:
        return math.nan, math.nan
    return t_power(test["diff"] / se, df), detectable(df) * se


def _pairs(first: dict[int, float], second: dict[int, float]) -> tuple[list[float], list[float]]:
    seeds = sorted(set(first) & set(second))
    return [first[k] for k in seeds], [second[k] for k in seeds]


def analyse(records: Sequence[dict]) -> tuple[list[dict], list[dict]]:
    """(directional rows, non-inferiority rows) of a report's judged claims (``records``:
    :attr:`.judge.Judge.claim_records`): each row the record with "welch" and "paired" (their
    dicts), for directional claims "power", "mdd", "paired_power", "paired_mdd" and the Holm-adjusted
    "holm" and "paired_holm" across the directional rows."""
    detectable = _Detectable()
    directional, non_inferior = [], []
    for record in records:
        if not record["word"].startswith(JUDGED):
            continue
        a = list(record["first"].values())
        b = list(record["second"].values())
        pa, pb = _pairs(record["first"], record["second"])
        row = {**record, "welch": welch(a, b), "paired": paired(pa, pb)}
        if record["margin"] is None:
            row["power"], row["mdd"] = _power(row["welch"], row["welch"]["df"], detectable)
            row["paired_power"], row["paired_mdd"] = _power(row["paired"], row["paired"]["n"] - 1, detectable)
            directional.append(row)
        else:
            non_inferior.append(row)
    for key, test in (("holm", "welch"), ("paired_holm", "paired")):
        for row, p in zip(directional, holm([row[test]["p"] for row in directional]), strict=True):
            row[key] = p
    return directional, non_inferior


def directional_tables(rows: Sequence[dict]) -> str:
    """The two tables of the directional claims: the protocol's test, and paired by seed."""
    welch_rows = ["| claim | protocol's verdict | difference ± 95% CI (Welch) | p | Holm p | power at the "
                  "difference | detected with 80% power | reading with Holm |",
                  "|---|---|---|---|---|---|---|---|"]
    paired_rows = ["| claim | seeds | difference ± 95% CI (paired) | first better on | p | Holm p | "
                   "power at the difference | detected with 80% power | reading | reading with Holm |",
                   "|---|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        w, p = row["welch"], row["paired"]
        welch_rows.append(
            f"| {row['text']} | {base_word(row['word'])} | {w['diff']:+.2f} ± {w['half']:.2f} | "
            f"{_pvalue(w['p'])} | {_pvalue(row['holm'])} | {row['power']:.2f} | {row['mdd']:.2f} | "
            f"{_reading(w['diff'], row['holm'])} |")
        paired_rows.append(
            f"| {row['text']} | {p['n']} | {p['diff']:+.2f} ± {p['half']:.2f} | {p['a_lower']} of {p['n']} | "
            f"{_pvalue(p['p'])} | {_pvalue(row['paired_holm'])} | {row['paired_power']:.2f} | "
            f"{row['paired_mdd']:.2f} | {_ci_reading(p['diff'], p['half'])} | "
            f"{_reading(p['diff'], row['paired_holm'])} |")
    return "\n".join(welch_rows) + "\n\n" + "\n".join(paired_rows)


def non_inferiority_table(rows: Sequence[dict]) -> str:
    lines = ["| claim | margin | protocol's verdict (by the mean) | difference ± 95% CI (Welch) | "
             "upper bound | by the bound | paired: difference ± 95% CI | upper bound | by the bound |",
             "|---|---|---|---|---|---|---|---|---|"]
    for row in rows:
        w, p, m = row["welch"], row["paired"], row["margin"]
        lines.append(
            f"| {row['text']} | {m:+.1f} | {base_word(row['word'])} | {w['diff']:+.2f} ± {w['half']:.2f} | "
            f"{w['diff'] + w['half']:+.2f} | {non_inferiority(w['diff'], w['half'], m)} | "
            f"{p['diff']:+.2f} ± {p['half']:.2f} | {p['diff'] + p['half']:+.2f} | "
            f"{non_inferiority(p['diff'], p['half'], m)} |")
    return "\n".join(lines)


def _steps(data: tuple, level: float) -> tuple[list[float | None], list[float]]:
    """Per seed of a series (steps, curves, summaries), the first evaluation step at or below
    ``level`` (None: never) and the seed's training budget."""
    steps, curves, summaries = data[0], data[1], data[2]
    return ([steps_to_level(steps, c, level) for c in curves],
            [float(s["config"]["total_steps"]) for s in summaries])


def speed_table(speeds: Sequence[tuple[str, dict, str]]) -> str:
    """Per panel and series: the steps to sparse's final level over the seeds that reach it (as the
    panel's line reads them) and with the others counted at their budget, and the ratio of the
    latter to sparse's, with its bound."""
    lines = ["| panel | sparse's final level | method | seeds reaching it | mean steps, reaching seeds "
             "only | mean steps, the others at the budget | ratio to sparse, the others at the budget |",
             "|---|---|---|---|---|---|---|"]
    for heading, data, sparse_label in speeds:
        level = sum(final_level(c) for c in data[sparse_label][1]) / len(data[sparse_label][1])
        s_reached, s_budgets = _steps(data[sparse_label], level)
        s_mean, s_n = censored_mean(s_reached, s_budgets)
        for label, series in data.items():
            reached, budgets = _steps(series, level)
            mean, n = censored_mean(reached, budgets)
            only = [x for x in reached if x is not None]
            only_text = f"{sum(only) / len(only):,.0f}" if only else "–"
            if label == sparse_label:
                ratio = "1.00"
            else:
                bound = {(True, True): "", (True, False): "≥", (False, True): "≤"}.get(
                    (s_n == len(s_reached), n == len(reached)), "?")
                ratio = f"{bound}{mean / s_mean:.2f}"
            lines.append(f"| {heading} | {level:.2f} | {label} | {n} of {len(reached)} | {only_text} | "
                         f"{mean:,.0f} | {ratio} |")
    return "\n".join(lines)


def changes(directional: Sequence[dict], non_inferior: Sequence[dict]) -> list[str]:
    """One line per claim whose reading changes under pairing, power or Holm."""
    out = []
    for row in directional:
        word = base_word(row["word"])
        w, p = row["welch"], row["paired"]
        notes = []
        if word == "not resolved" and row["power"] < POWER:
            notes.append(f"under-powered under its own test (power {row['power']:.2f} at the observed "
                         f"difference; 80% power needs {row['mdd']:.2f} steps)")
        holm_word = _reading(w["diff"], row["holm"])
        if holm_word != word:
            notes.append(f"{holm_word} with Holm (adjusted p {_pvalue(row['holm'])})")
        paired_word = _ci_reading(p["diff"], p["half"])
        if paired_word != word:
            notes.append(f"{paired_word} paired by seed ({p['diff']:+.2f} ± {p['half']:.2f}, first better on "
                         f"{p['a_lower']} of {p['n']} seeds)")
        paired_holm = _reading(p["diff"], row["paired_holm"])
        if paired_holm != word:
            notes.append(f"{paired_holm} paired with Holm (adjusted p {_pvalue(row['paired_holm'])})")
        if notes:
            out.append(f"- **{row['text']}** (protocol: {word}): " + "; ".join(notes))
    for row in non_inferior:
        word = base_word(row["word"])
        w, p, m = row["welch"], row["paired"], row["margin"]
        by_bound = non_inferiority(w["diff"], w["half"], m)
        paired_bound = non_inferiority(p["diff"], p["half"], m)
        notes = []
        if by_bound != word:
            notes.append(f"{by_bound} by the bound (upper {w['diff'] + w['half']:+.2f} against {m:+.1f})")
        if paired_bound != word:
            notes.append(f"{paired_bound} by the paired bound (upper {p['diff'] + p['half']:+.2f})")
        if notes:
            out.append(f"- **{row['text']}** (protocol: {word}): " + "; ".join(notes))
    return out


def planning_text(planning_sd: float | None, seeds: int) -> str:
    """What the protocol's power planning reads with its own test: the difference ``seeds`` seeds a
    side detect with 80% power at ``planning_sd`` (Welch standard error, df = seeds - 1)."""
    if planning_sd is None or seeds < 2:
        return ""
    se = planning_sd * math.sqrt(2 / seeds)
    mdd = detectable_delta(seeds - 1, POWER) * se
    return (f" The protocol planned its power at a seed-to-seed SD of {planning_sd:g} steps with normal "
            f"quantiles; with its own test (Welch, {seeds} seeds a side, t on df = {seeds - 1}) the "
            f"difference detected with 80% power at that SD is {mdd:.1f} steps. Its \"under-powered\" label "
            "compared a CI half-width with the normal-quantile figure; the power columns below replace it.")


def posthoc_section(claim_records: Sequence[dict], speeds: Sequence[tuple[str, dict, str]], date: str,
                    planning_sd: float | None = None, fixed_episodes: bool = True) -> str | None:
    """The section (``claim_records``: the claims judged, :attr:`.judge.Judge.claim_records`;
    ``speeds``: the panels with a steps-to-sparse's-level line, :attr:`.build.Report.speeds`; ``planning_sd``:
    the SD the protocol planned its power with; ``fixed_episodes``: whether the runs were evaluated
    on fixed episodes, the same for every method of a seed, rather than the legacy window); None
    when no claim was judged."""
    shared = ("that seed's fixed evaluation episodes and seeding" if fixed_episodes
              else "that seed's seeding (of the networks, the training and the evaluation environments)")
    directional, non_inferior = analyse(claim_records)
    if not directional and not non_inferior:
        return None
    seeds = max((row["welch"]["df"] + 1 for row in directional), default=0)
    parts = [f"## Added after the protocol ({date}): paired by seed, power, non-inferiority by its bound, "
             "censored speed-ups, Holm",
             f"Exploratory: added after the protocol ({date}) and computed from the same runs; every verdict "
             f"above stays as the protocol judged it. The runs of a seed share {shared}, so the design is "
             "paired by seed, while the protocol's test is unpaired (Welch). For each directional claim "
             "with a verdict: the protocol's test and the paired one (per seed, first − second; their mean "
             "with a 95% CI, Student t, df = n − 1; on how many seeds the first was better), each with its "
             "two-sided p-value, the p-value adjusted across the "
             f"{len(directional)} directional claims by Holm's step-down method (family-wise 5%), the power "
             "at the observed difference and the difference detected with 80% power, both from the "
             "noncentral t of that test (its standard error and df)." + planning_text(planning_sd, seeds)
             + (" Learned teams keep only each evaluation's mean episode length, so they are paired by "
                "seed, not by episode; the comparison with the classical controllers on each seed's own "
                "evaluation episodes (under each panel) is the paired one there, the protocol's is on the "
                "reference episodes." if speeds else "")]
    if directional:
        parts.append(directional_tables(directional))
    if non_inferior:
        parts.append("**Non-inferiority by its bound.** \"At worst matches\" holds when the 95% CI's upper "
                     "bound is within the margin, did not hold when its lower bound is beyond it, and is "
                     "inconclusive otherwise (the protocol judged the mean):\n\n"
                     + non_inferiority_table(non_inferior))
    if speeds:
        parts.append("**Steps to MDRL-sparse's final level, censored.** The panels' lines average the seeds "
                     "that reach the level; here a seed that never does counts its whole training budget, "
                     "so a mean with such a seed is a lower bound, and the ratio to sparse's is a lower "
                     "bound (\"≥\", the method's side), an upper bound (\"≤\", sparse's side) or bounded "
                     "neither way (\"?\", both):\n\n" + speed_table(speeds))
    changed = changes(directional, non_inferior)
    parts.append("**Readings that change** under pairing, power or Holm:\n\n"
                 + ("\n".join(changed) if changed else "none."))
    return "\n\n".join(parts)
