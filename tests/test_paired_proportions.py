"""Intervals of the paired guard (gac_jax.evaluation.paired_proportions) against independent
calculations and by simulation at the margin.

A discordant table is pinned to scipy.stats' exact binomial intervals combined by hand, and a
frame-clustered one to a float64 hand computation of its design effect. The simulation draws
guard sets whose true found-rate difference is exactly the margin (-0.5 points), with
discordances of independent objects or of whole frames (2.7 objects per frame, as the hard
difficulty), and looks at them the way the guard is used (one look, and four looks on growing
frame sets, the alpha spent per look): P(within) must stay at most alpha, within three
standard errors of the simulation. The object-level interval with one alpha for every look
fails the same check on clustered discordances, so the check can fail.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from gac_jax.evaluation import paired_proportions as pp

MARGIN, ALPHA = 0.5, 0.05
RUNS = 1500
LOOKS = (500, 1000, 2000, 4000)  # frames at each look (nested, growing)


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


def _simulate(q: float, lost: float, clustered: bool, seed: int, interval) -> tuple[float, float]:
    """``(P(within at look 1), P(within at any of the looks))`` over ``RUNS`` guard runs of a
    true found-rate difference of exactly -``MARGIN`` points: each object (independent) or
    each frame (clustered: all its objects) is discordant with probability ``q``, lost with
    probability ``lost`` (``q (2 lost - 1) = MARGIN / 100``)."""
    assert q * (2 * lost - 1) == pytest.approx(MARGIN / 100)
    rng = np.random.default_rng(seed)
    acc = {k: np.zeros(RUNS) for k in ("n", "r", "c", "n2", "d2", "dn", "df")}
    within_any, first, done = np.zeros(RUNS, bool), None, 0
    for look, frames in enumerate(LOOKS, 1):
        shape = (RUNS, frames - done)
        done = frames
        n = 1.0 + rng.poisson(1.7, shape)
        if clustered:
            hit, gone = rng.random(shape) < q, rng.random(shape) < lost
            r, c = np.where(hit & gone, n, 0.0), np.where(hit & ~gone, n, 0.0)
        else:
            m = rng.binomial(n.astype(np.int64), q)
            r = rng.binomial(m, lost).astype(np.float64)
            c = m - r
        d = c - r
        for key, v in (
            ("n", n),
            ("r", r),
            ("c", c),
            ("n2", n * n),
            ("d2", d * d),
            ("dn", d * n),
            ("df", (r + c) > 0),
        ):
            acc[key] += v.sum(axis=1)
        delta = (acc["c"] - acc["r"]) / acc["n"]
        sums = {  # frame_sums of the frames so far, accumulated look by look
            "n": acc["n"],
            "ref_only": acc["r"],
            "cand_only": acc["c"],
            "frames": np.full(RUNS, float(frames)),
            "discordant_frames": acc["df"],
            "n_squared": acc["n2"],
            "cluster_ss": acc["d2"] - 2 * delta * acc["dn"] + delta**2 * acc["n2"],
        }
        lo, hi = interval(sums, look)
        within = (lo >= -MARGIN) & (hi <= MARGIN)
        within_any |= within
        first = within.mean() if first is None else first
    return float(first), float(within_any.mean())


def _guard(sums, look):
    return pp.clustered_interval(sums, pp.look_alpha(ALPHA, look))[:2]


def _objects_one_alpha(sums, look):
    """The earlier rule: objects independent, alpha at every look."""
    return pp.difference_interval(sums["ref_only"], sums["cand_only"], sums["n"], ALPHA)


BOUND = ALPHA + 3 * math.sqrt(ALPHA * (1 - ALPHA) / RUNS)  # 3 standard errors of the simulation


@pytest.mark.parametrize(
    "q, lost, clustered",
    [(0.005, 1.0, False), (0.02, 0.625, False), (0.005, 1.0, True), (0.02, 0.625, True)],
)
def test_within_at_the_margin_is_rare_for_independent_and_clustered_objects(q, lost, clustered):
    one_look, four_looks = _simulate(q, lost, clustered, seed=11, interval=_guard)
    assert one_look <= BOUND and four_looks <= BOUND, (one_look, four_looks)


def _objects_spent(sums, look):
    """Alpha spent over looks, but objects independent (no design effect)."""
    a = pp.look_alpha(ALPHA, look)
    return pp.difference_interval(sums["ref_only"], sums["cand_only"], sums["n"], a)


@pytest.mark.parametrize("interval", [_objects_one_alpha, _objects_spent])
def test_the_simulation_catches_an_interval_that_ignores_frames(interval):
    one_look, four_looks = _simulate(0.005, 1.0, True, seed=12, interval=interval)
    assert four_looks > BOUND, four_looks
