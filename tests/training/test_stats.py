"""One statistics module: curve bands, table CIs and claim CIs are all Student t."""

import math

import pytest
from medc_training.stats import compare, curve_band, mean_ci, percentile, t95


def test_curve_bands_use_student_t_like_the_claims():
    curves = [[1.0, 4.0], [2.0, 6.0], [3.0, 8.0]]  # 3 seeds: df 2, t = 4.303
    mean, half = curve_band(curves)
    assert mean.tolist() == [2.0, 6.0]
    assert half[0] == pytest.approx(4.303 * 1.0 / math.sqrt(3))
    assert half[1] == pytest.approx(4.303 * 2.0 / math.sqrt(3))
    m, h = mean_ci([c[0] for c in curves])
    assert (m, h) == pytest.approx((mean[0], half[0]))
    assert curve_band([[5.0, 5.0]])[1].tolist() == [0.0, 0.0]


def test_t_quantiles_and_welch_difference():
    assert t95(1) == 12.706 and t95(12) == 2.228 and t95(100) == 1.96 and t95(0) == math.inf
    c = compare([1.0, 2.0, 3.0], [2.0, 3.0, 4.0])
    assert c["diff"] == pytest.approx(-1.0)
    assert c["half"] == pytest.approx(4.303 * math.sqrt(1 / 3 + 1 / 3))


def test_percentile_is_the_nearest_rank_value():
    assert percentile([3.0, 1.0, 2.0], 50) == 2.0
    values = [float(v) for v in range(1, 101)]  # rank round(0.99 * 99) = 98 of the sorted values
    assert percentile(values, 99) == 99.0
    assert percentile(values, 0) == 1.0 and percentile(values, 100) == 100.0
    assert percentile([7.0], 99) == 7.0
