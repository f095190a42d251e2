"""Paired comparisons, the t and noncentral-t distributions, power, non-inferiority by its bound,
censored means and Holm, against hand-computed values and closed forms."""

import math

import numpy as np
import pytest
from medc_training.stats import (
    censored_mean,
    compare,
    detectable_delta,
    holm,
    nct_cdf,
    non_inferiority,
    norm_cdf,
    paired,
    t95,
    t_cdf,
    t_power,
    t_pvalue,
    t_quantile,
    welch,
)


def test_paired_difference_ci_and_signs_by_hand():
    a = [30.0, 28.0, 33.0, 29.0, 31.0]
    b = [27.0, 27.0, 30.0, 26.0, 30.0]
    # differences 3 1 3 3 1: mean 2.2, squared deviations 0.64 1.44 0.64 0.64 1.44 sum to 4.8
    p = paired(a, b)
    sd = math.sqrt(4.8 / 4)
    se = sd / math.sqrt(5)
    assert p["n"] == 5 and p["diff"] == pytest.approx(2.2)
    assert p["sd"] == pytest.approx(sd) and p["half"] == pytest.approx(2.776 * se)
    assert p["half"] == pytest.approx(1.35995, abs=1e-5)
    assert (p["a_lower"], p["b_lower"]) == (0, 5)
    t = 2.2 / se
    assert p["t"] == pytest.approx(t)
    # df 4: P(|T| <= t) = t (t^2 + 6) / (t^2 + 4)^(3/2)
    assert p["p"] == pytest.approx(1 - t * (t * t + 6) / (t * t + 4) ** 1.5, rel=1e-9)
    # the unpaired test on the same numbers does not resolve what pairing does
    assert compare(a, b)["half"] > 2.2 > p["half"]


def test_paired_ties_and_too_few_pairs():
    p = paired([1.0, 2.0, 3.0], [1.0, 3.0, 2.0])
    assert (p["a_lower"], p["b_lower"]) == (1, 1) and p["diff"] == 0.0 and p["p"] == pytest.approx(1.0)
    one = paired([4.0], [1.0])
    assert one["diff"] == 3.0 and one["half"] == math.inf and math.isnan(one["p"])
    with pytest.raises(ValueError):
        paired([1.0, 2.0], [1.0])


def test_welch_p_value_is_that_of_its_own_ci():
    a, b = [1.0, 2.0, 3.0], [2.0, 3.0, 4.0]
    w = welch(a, b)
    se = math.sqrt(1 / 3 + 1 / 3)
    assert w["df"] == 2 and w["se"] == pytest.approx(se) and w["t"] == pytest.approx(-1.0 / se)
    # df 2: P(|T| <= t) = t / sqrt(2 + t^2)
    t = 1.0 / se
    assert w["p"] == pytest.approx(1 - t / math.sqrt(2 + t * t))
    # the CI excludes 0 exactly when p < 0.05
    assert t_pvalue(t95(4), 4) == pytest.approx(0.05, abs=2e-4)


def test_t_cdf_closed_forms_and_quantiles_match_the_table():
    for t in (-3.0, -0.4, 0.0, 1.0, 7.5):
        assert t_cdf(t, 1) == pytest.approx(0.5 + math.atan(t) / math.pi, abs=1e-12)  # Cauchy
        assert t_cdf(t, 2) == pytest.approx(0.5 + t / (2 * math.sqrt(2 + t * t)), abs=1e-12)
        assert t_cdf(t, 3) == pytest.approx(0.5 + (math.atan(t / math.sqrt(3))
                                                   + math.sqrt(3) * t / (3 + t * t)) / math.pi, abs=1e-12)
    assert t_quantile(0.975, 1) == pytest.approx(math.tan(0.475 * math.pi), rel=1e-9)
    assert t_quantile(0.975, 2) == pytest.approx(0.95 * math.sqrt(2 / (1 - 0.95 ** 2)), rel=1e-9)
    for df in (3, 4, 5, 6, 7, 8, 9, 10, 15, 20, 30):
        assert round(t_quantile(0.975, df), 3) == t95(df)
    assert t_quantile(0.025, 4) == pytest.approx(-t_quantile(0.975, 4))


def test_noncentral_t_reduces_to_known_values():
    # no noncentrality: the Student t, also at fractional df (against the closed forms either side)
    for df in (1, 2, 4, 9):
        for t in (-2.5, 0.3, 1.7):
            assert nct_cdf(t, df, 0.0) == pytest.approx(t_cdf(t, df), abs=1e-8)
    assert t_cdf(1.5, 3) < nct_cdf(1.5, 3.5, 0.0) < t_cdf(1.5, 4)
    # P(T <= 0) = P(Z + delta <= 0) = Phi(-delta), whatever the df
    for df, delta in ((1, 0.7), (4, 2.0), (12, -1.1)):
        assert nct_cdf(0.0, df, delta) == pytest.approx(norm_cdf(-delta), abs=1e-9)


def test_noncentral_t_against_simulation():
    rng = np.random.default_rng(20261203)
    n = 400_000
    for df, delta, t in ((1, 3.0, 2.0), (4, 3.76, 2.776), (15, 2.0, 2.131)):
        draws = (rng.standard_normal(n) + delta) / np.sqrt(rng.chisquare(df, n) / df)
        assert nct_cdf(t, df, delta) == pytest.approx(float(np.mean(draws <= t)), abs=0.003)


def test_power_and_detectable_difference_of_the_t_test():
    # the level: no true difference is detected 5% of the time
    assert t_power(0.0, 4) == pytest.approx(0.05, abs=1e-9)
    # one-sample t test, n = 10, effect size 1 (delta = sqrt(10), df 9): power 0.8031 (the
    # textbook value of power tables)
    assert t_power(math.sqrt(10), 9) == pytest.approx(0.8031, abs=1e-4)
    d4 = detectable_delta(4)
    assert t_power(d4, 4) == pytest.approx(0.8, abs=1e-5)
    # with 5 seeds a side at SD 3.4 (Welch SE 3.4 sqrt(2/5), df 4) the t test detects about 8.1
    # steps with 80% power; normal quantiles would say (1.96 + 0.84) * SE, about 6.0
    assert d4 * 3.4 * math.sqrt(2 / 5) == pytest.approx(8.09, abs=0.01)
    assert (1.96 + 0.8416) * 3.4 * math.sqrt(2 / 5) == pytest.approx(6.02, abs=0.01)
    # many degrees of freedom: the normal approximation
    assert detectable_delta(2000) == pytest.approx(1.95996 + 0.84162, abs=0.01)


def test_non_inferiority_is_judged_by_the_bound():
    # mean inside the 2-step margin, upper bound outside: inconclusive
    assert non_inferiority(0.15, 5.65, 2.0) == "inconclusive"
    assert non_inferiority(0.5, 1.0, 2.0) == "held"
    assert non_inferiority(2.5, 1.0, 2.0) == "inconclusive"
    assert non_inferiority(3.1, 1.0, 2.0) == "did not hold"
    assert non_inferiority(math.nan, 1.0, 2.0) == "not run"


def test_censored_mean_counts_non_reaching_seeds_at_the_budget():
    # one seed of five reaches the level at 81,920 steps, four never do in 250,000
    random5, reached = censored_mean([81_920.0, None, None, None, None], [250_000.0] * 5)
    assert (random5, reached) == (pytest.approx(216_384.0), 1)
    # four seeds reach it at a mean of 177,408 steps, one does not
    sparse, reached = censored_mean([163_840.0, 180_224.0, 180_224.0, 185_344.0, None], [250_000.0] * 5)
    assert (sparse, reached) == (pytest.approx(191_926.4), 4)
    assert random5 / sparse == pytest.approx(1.127, abs=1e-3)
    assert censored_mean([], []) == (pytest.approx(math.nan, nan_ok=True), 0)


def test_holm_step_down_by_hand():
    # sorted 0.005 0.01 0.03 0.04, times 4 3 2 1: 0.02 0.03 0.06 0.04, running maximum 0.02 0.03 0.06 0.06
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    adjusted = holm([0.2, math.nan, 0.01])  # nan is not in the family: m = 2
    assert adjusted[0] == pytest.approx(0.2) and math.isnan(adjusted[1])
    assert adjusted[2] == pytest.approx(0.02)
    assert holm([0.6, 0.7]) == pytest.approx([1.0, 1.0])
