"""``magenv.stats.paired_ratio``: paired ratio, bootstrap interval, win rate, interquartile-mean ratio."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magenv.stats import paired_ratio


def test_a_constant_ratio_is_exact():
    ref = np.array([1.0, 2.0, 4.0, 0.5])
    p = paired_ratio(0.5 * ref, ref)
    assert p.n == 4 and p.ratio == pytest.approx(0.5, rel=1e-12)
    assert p.low == pytest.approx(0.5, rel=1e-12) and p.high == pytest.approx(0.5, rel=1e-12)
    assert p.win_rate == 1.0 and p.level == 0.95


def test_geometric_mean_of_the_per_unit_ratios_and_the_swap_gives_the_reciprocal():
    rng = np.random.default_rng(1)
    ref = rng.uniform(0.5, 3.0, 12)
    method = ref * np.exp(rng.normal(-0.2, 0.3, 12))
    p, q = paired_ratio(method, ref, seed=3), paired_ratio(ref, method, seed=3)
    assert p.ratio == pytest.approx(math.exp(np.mean(np.log(method / ref))), rel=1e-12)
    assert q.ratio == pytest.approx(1 / p.ratio, rel=1e-12)
    # the same resamples: the interval maps onto the reciprocal one
    assert q.low == pytest.approx(1 / p.high, rel=1e-9) and q.high == pytest.approx(1 / p.low, rel=1e-9)
    assert p.win_rate + q.win_rate == pytest.approx(1.0)
    assert p.low < p.ratio < p.high


def test_win_rate_counts_ties_as_half():
    p = paired_ratio([1.0, 2.0, 3.0, 5.0], [2.0, 2.0, 1.0, 6.0])
    assert p.win_rate == pytest.approx((1 + 0.5 + 0 + 1) / 4)


def test_the_interval_is_seeded():
    rng = np.random.default_rng(2)
    ref, method = rng.uniform(1, 2, 9), rng.uniform(1, 2, 9)
    a, b, c = (paired_ratio(method, ref, seed=s) for s in (7, 7, 8))
    assert (a.low, a.high) == (b.low, b.high)
    assert (a.low, a.high) != (c.low, c.high)


def test_the_interval_covers_the_true_ratio_about_95_percent_of_the_time():
    """Log-normal per-unit ratios around a known geometric mean (0.8): over 200 experiments of 30 units the
    bootstrap interval holds 0.8 in about 95 % of them (percentile bootstrap: a little less at n = 30)."""
    rng = np.random.default_rng(0)
    hits = 0
    for k in range(200):
        ref = rng.uniform(0.5, 4.0, 30)
        method = ref * 0.8 * np.exp(rng.normal(0.0, 0.4, 30))
        p = paired_ratio(method, ref, n_boot=1000, seed=k)
        hits += p.low <= 0.8 <= p.high
    assert 0.88 <= hits / 200 <= 0.99


def test_many_units_stay_within_memory_and_agree_with_a_normal_interval():
    rng = np.random.default_rng(4)
    n = 5000
    log_ratio = rng.normal(-0.1, 0.5, n)
    ref = rng.uniform(1, 3, n)
    p = paired_ratio(ref * np.exp(log_ratio), ref, n_boot=2000)
    half = 1.96 * log_ratio.std(ddof=1) / math.sqrt(n)
    assert math.log(p.low) == pytest.approx(log_ratio.mean() - half, abs=0.005)
    assert math.log(p.high) == pytest.approx(log_ratio.mean() + half, abs=0.005)


def test_one_pair_has_no_interval():
    p = paired_ratio([1.0], [2.0])
    assert p.ratio == 0.5 and p.win_rate == 1.0 and math.isnan(p.low) and math.isnan(p.high)
    assert p.iqm == 0.5 and math.isnan(p.iqm_low) and math.isnan(p.iqm_high)


@pytest.mark.parametrize(
    ("method", "reference", "kw", "message"),
    [
        ([1.0, 2.0], [1.0], {}, "pair unit by unit: 2 errors against 1"),
        ([], [], {}, "non-empty 1-D"),
        ([[1.0, 2.0]], [[1.0, 2.0]], {}, "non-empty 1-D"),
        ([1.0, 0.0], [1.0, 1.0], {}, "method: errors must be finite and > 0 for a ratio; entry 1 is 0.0"),
        ([1.0, 1.0], [1.0, float("nan")], {}, "reference: errors must be finite and > 0"),
        ([1.0, 1.0], [1.0, 1.0], {"n_boot": 0}, "n_boot must be an integer ≥ 1"),
        ([1.0, 1.0], [1.0, 1.0], {"level": 1.0}, "level must be in (0, 1)"),
    ],
)
def test_bad_input_is_named(method, reference, kw, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        paired_ratio(method, reference, **kw)


def test_the_interquartile_mean_ratio_drops_a_quarter_of_the_units_at_each_end():
    log_ratio = np.log([0.1, 0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 30.0])  # n = 8: two dropped at each end
    ref = np.linspace(1.0, 2.0, 8)
    p = paired_ratio(ref * np.exp(log_ratio), ref)
    assert p.iqm == pytest.approx(math.exp(np.mean(np.log([0.6, 0.7, 0.8, 0.9]))), rel=1e-12)
    assert p.iqm_low <= p.iqm <= p.iqm_high


def test_one_extreme_unit_moves_the_geometric_mean_but_not_the_interquartile_mean():
    ref = np.linspace(1.0, 3.0, 20)
    method = 0.8 * ref
    method[3] = 100.0 * ref[3]
    p = paired_ratio(method, ref)
    assert p.iqm == pytest.approx(0.8, rel=1e-12) and p.iqm_high == pytest.approx(0.8, rel=1e-12)
    assert p.ratio > 1.0 and p.high > 1.0  # the geometric mean is pulled above 1 by the one unit
    assert p.win_rate == pytest.approx(19 / 20)


def test_the_swap_gives_the_reciprocal_interquartile_mean_and_interval():
    rng = np.random.default_rng(5)
    ref = rng.uniform(0.5, 3.0, 15)
    method = ref * np.exp(rng.normal(0.1, 0.6, 15))
    p, q = paired_ratio(method, ref, seed=2), paired_ratio(ref, method, seed=2)
    assert q.iqm == pytest.approx(1 / p.iqm, rel=1e-12)
    assert q.iqm_low == pytest.approx(1 / p.iqm_high, rel=1e-9) and q.iqm_high == pytest.approx(1 / p.iqm_low, rel=1e-9)


@settings(derandomize=True, deadline=None, max_examples=60)
@given(st.lists(st.tuples(st.floats(0.01, 100.0), st.floats(0.01, 100.0)), min_size=2, max_size=30))
def test_any_pairs_give_ordered_intervals_within_the_unit_ratios_and_reciprocal_swaps(pairs):
    method, ref = np.array(pairs).T
    p, q = paired_ratio(method, ref, n_boot=200, seed=1), paired_ratio(ref, method, n_boot=200, seed=1)
    lo, hi = (method / ref).min() * (1 - 1e-12), (method / ref).max() * (1 + 1e-12)
    for est, low, high in ((p.ratio, p.low, p.high), (p.iqm, p.iqm_low, p.iqm_high)):
        assert lo <= low <= high <= hi and lo <= est <= hi
    assert q.iqm == pytest.approx(1 / p.iqm, rel=1e-9) and q.iqm_low == pytest.approx(1 / p.iqm_high, rel=1e-9)


def test_the_texts_give_each_estimate_with_its_interval():
    p = paired_ratio([1.0, 2.0, 3.0, 4.0], [2.0, 2.0, 2.0, 2.0])
    assert p.ratio_text(2) == f"{p.ratio:.2f} [{p.low:.2f}, {p.high:.2f}]"
    assert p.iqm_text() == f"{p.iqm:.3f} [{p.iqm_low:.3f}, {p.iqm_high:.3f}]"
