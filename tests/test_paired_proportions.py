"""Paired proportions (gac_jax.guard.paired_proportions) against independent
calculations: a discordant table is pinned to scipy.stats' exact binomial intervals combined
by hand, McNemar and Holm to hand values, the earlier rule's design effect to a float64 hand
computation, and the alpha spent over looks. The guard's current count intervals and their
simulations at the margin: tests/test_frame_betting.py.
"""

from __future__ import annotations

import numpy as np
import pytest

from gac_jax.guard import paired_proportions as pp

MARGIN, ALPHA = 0.5, 0.05


def test_a_discordant_table_against_scipy_and_by_hand():
    stats = pytest.importorskip("scipy.stats")
    ref_only, cand_only, n, a = 12, 3, 2000, 0.05
    q_lo, q_hi = stats.binomtest(15, n).proportion_ci(1 - a, "exact")  # a / 2 each side
    p_lo, p_hi = stats.binomtest(cand_only, 15).proportion_ci(1 - a, "exact")
    low = 100 * min(q_lo * (2 * p_lo - 1), q_hi * (2 * p_lo - 1))
    high = 100 * max(q_lo * (2 * p_hi - 1), q_hi * (2 * p_hi - 1))
    assert pp.difference_interval(ref_only, cand_only, n, a) == pytest.approx((low, high), 1e-9)
    # p_lo < 1/2 < p_hi: the bounds take q_hi; the interval holds the observed -0.45 points
    assert low == pytest.approx(100 * q_hi * (2 * p_lo - 1))
    assert low < -0.45 < high
    # the bisection of the binomial cdf and the beta distribution give the same bounds
    for x, m in ((0, 10), (3, 10), (10, 10), (50, 1000), (7, 31)):
        bounds = tuple(float(b) for b in pp.beta_bounds(x, m, 0.025))
        assert pp.clopper_pearson(x, m, 0.025) == pytest.approx(bounds, abs=1e-12)
        lo = stats.beta.ppf(0.025, x, m - x + 1) if x else 0.0
        hi = stats.beta.ppf(0.975, x + 1, m - x) if x < m else 1.0
        assert pp.clopper_pearson(x, m, 0.025) == pytest.approx((lo, hi), abs=1e-9)
    # no discordant object: +-(upper bound of the discordant share), 736 objects = 0.5 points
    lo, hi = pp.difference_interval(0, 0, 736, 0.05)
    assert lo == -hi and hi == pytest.approx(100 * (1 - 0.025 ** (1 / 736)), abs=1e-9)
    assert pp.mcnemar_p(0, 6) == pytest.approx(2 / 64)
    assert pp.holm([0.01, 0.04, 0.03]) == pytest.approx([0.03, 0.06, 0.06])


def test_the_design_effect_by_hand():
    # 40 frames of 3 objects: 10 frames lose all 3 (30 lost), 20 frames gain 1 (20 gained)
    n_f = np.full(40, 3.0)
    ref_f = np.r_[np.full(10, 3.0), np.zeros(30)]
    cand_f = np.r_[np.zeros(10), np.ones(20), np.zeros(10)]
    sums = pp.frame_sums(n_f, ref_f, cand_f)
    delta = (20 - 30) / 120
    d = cand_f - ref_f
    v_cluster = 40 / 39 * np.sum((d - delta * n_f) ** 2) / 120**2
    v_objects = (50 / 120 - delta**2) / 120
    deff = v_cluster / v_objects  # 30 discordant frames: estimated, not the worst case
    assert deff > 1 and pp.design_effect(sums) == pytest.approx(deff)
    lo, hi, got = pp.clustered_interval(sums, 0.05)
    assert got == pytest.approx(deff)
    assert (lo, hi) == pytest.approx(pp.difference_interval(30 / deff, 20 / deff, 120 / deff, 0.05))
    # fewer discordant frames: at least the worst case, all of a frame's objects together
    few = pp.frame_sums(n_f, np.r_[3.0, np.zeros(39)], np.zeros(40))
    d, delta = np.r_[-3.0, np.zeros(39)], -3 / 120
    estimated = (40 / 39 * np.sum((d - delta * 3) ** 2) / 120**2) / ((3 / 120 - delta**2) / 120)
    assert pp.design_effect(few) == pytest.approx(max(3.0, estimated))
    one = pp.frame_sums(np.r_[3.0, np.ones(39)], np.r_[0.0, np.ones(10), np.zeros(29)], 0 * d)
    assert pp.design_effect(one) == pytest.approx((9 + 39) / 42)  # sum n_f^2 / sum n_f
    # independent objects (one per frame) have no design effect to correct
    assert pp.design_effect(pp.frame_sums(np.ones(50), np.ones(50) * 0, np.ones(50))) == 1.0


def test_looks_spend_at_most_alpha():
    spent = [pp.look_alpha(ALPHA, k) for k in range(1, 30)]
    assert spent[0] == ALPHA / 2 and sum(spent) < ALPHA
    with pytest.raises(ValueError, match="looks count from 1"):
        pp.look_alpha(ALPHA, 0)
