"""Paired differences of proportions: exact binomial intervals, McNemar and Holm, alpha spent
over looks, and the guard's earlier frame-clustered interval.

Two runs are scored on the same objects; each object is *found* or *missed* by each run,
giving the 2x2 table ``both``, ``ref_only`` (lost by the candidate), ``cand_only`` (gained),
``neither`` of ``n`` objects. The difference of found-rates is
``delta = (cand_only - ref_only) / n``, reported in points (percent of the objects).

**The conservative interval** (:func:`difference_interval`): ``delta = q (2 p - 1)`` with
``q`` the share of discordant objects (``ref_only + cand_only`` of ``n``) and ``p`` the share
of discordant objects the candidate found; Clopper-Pearson intervals for ``q`` and ``p``, each
at half the error level, bound ``delta`` together (Bonferroni). Its coverage is at least the
stated one when objects are independent; it is conservative (about 1.8 times the objects a
score interval for paired proportions would need), not exact. With no discordant object it is
``+-q_hi``, e.g. ``+-0.50`` points for 736 objects: agreement on few objects is no evidence of
equivalence.

**The earlier rule's frames as the unit** (:func:`clustered_interval`; the guard's count
criteria used it up to verdict rule version 2 and now use
:mod:`gac_jax.guard.frame_betting`; it stays to measure what the current intervals cost,
``benchmarks/bench_guard_power.py``, and to show that the burst simulations of the tests catch
it): objects of one frame move together (a
frame's exposure or a shared feature shifts every object in it), so the interval uses
*per-frame paired counts with a design-effect correction*: the counts are divided by the
design effect ``deff`` (Kish's effective sample size) before the conservative interval above
is applied to them (Clopper-Pearson takes non-integer counts through the beta distribution).
``deff`` is the ratio of the cluster-robust (linearised ratio, frames as clusters) variance of
``delta`` to its variance for independent objects, at least 1. With fewer than
:data:`MIN_DISCORDANT_FRAMES` frames holding a discordance it cannot be estimated, and the
worst case is taken instead: every object of a frame moving together,
``deff_max = sum(n_f^2) / sum(n_f)`` (``n_f`` the objects of frame ``f``). Its coverage at
the margin holds for independent and for frame-clustered discordances, but not when changes
come in rare large bursts: ``deff_max`` is an average frame size, not what one frame can
change, and a guard set holding no burst (or 30 frames of small background changes) shows
none. Under such bursts it said "within" at the margin in 10-20 % of guard runs.

**Looking again**: a guard run may be repeated on more frames until it decides. Look ``k``
(1, 2, ...) spends ``alpha / 2^k`` (:func:`look_alpha`); the looks together spend at most
``alpha`` whatever their number and spacing (Bonferroni over looks), so "within" after any
number of looks still holds at level ``alpha``.

Pure numpy and scipy (a JAX dependency); no JAX.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.special import betaincinv

MIN_DISCORDANT_FRAMES = 30  # below this, the design effect is the worst case deff_max


def look_alpha(alpha: float, look: int) -> float:
    """The error level spent at look ``look`` (1-based): ``alpha / 2**look``."""
    if look < 1:
        raise ValueError(f"looks count from 1, got {look}")
    return alpha / 2.0**look


# ----------------------------------------------------------------------------- exact binomial


_LOG_FACTORIALS = np.zeros(1)


def _log_factorials(n: int) -> np.ndarray:
    """``log k!`` for ``k = 0..n`` (cached, grown on demand)."""
    global _LOG_FACTORIALS
    if len(_LOG_FACTORIALS) <= n:
        k = np.arange(1, 2 * n + 2, dtype=np.float64)
        _LOG_FACTORIALS = np.concatenate([[0.0], np.cumsum(np.log(k))])
    return _LOG_FACTORIALS[: n + 1]


def binom_cdf(x: int, n: int, p: float) -> float:
    """``P(X <= x)`` for ``X ~ Binomial(n, p)``."""
    if x < 0:
        return 0.0
    if x >= n or p <= 0.0:
        return 1.0
    if p >= 1.0:
        return 0.0
    lf = _log_factorials(n)
    k = np.arange(x + 1)
    logs = lf[n] - lf[k] - lf[n - k] + k * math.log(p) + (n - k) * math.log1p(-p)
    top = logs.max()
    return float(min(1.0, math.exp(top) * np.exp(logs - top).sum()))


def _bisect(f, target: float, increasing: bool) -> float:
    """``p`` in [0, 1] with ``f(p) = target`` for a monotone ``f``."""
    lo, hi = 0.0, 1.0
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        below = f(mid) < target
        lo, hi = (mid, hi) if below == increasing else (lo, mid)
    return 0.5 * (lo + hi)


def clopper_pearson(x: int, n: int, alpha_each_side: float) -> tuple[float, float]:
    """Exact binomial interval for ``x`` successes of ``n`` (integers, by bisection of the
    binomial cdf): each bound has error ``alpha_each_side`` (``(0, 1)`` for ``n = 0``)."""
    if n == 0:
        return 0.0, 1.0
    a = alpha_each_side
    lower = 0.0 if x == 0 else _bisect(lambda p: 1.0 - binom_cdf(x - 1, n, p), a, True)
    upper = 1.0 if x == n else _bisect(lambda p: binom_cdf(x, n, p), a, False)
    return lower, upper


def beta_bounds(x, n, alpha_each_side: float) -> tuple[np.ndarray, np.ndarray]:
    """Clopper-Pearson bounds through the beta distribution, for real (effective) counts
    ``0 <= x <= n`` (arrays broadcast): ``(0, 1)`` where ``n == 0``."""
    x, n = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(n, np.float64))
    a = alpha_each_side
    with np.errstate(invalid="ignore", divide="ignore"):
        lo = np.where(x > 0, betaincinv(np.maximum(x, 1e-300), n - x + 1.0, a), 0.0)
        hi = np.where(x < n, betaincinv(x + 1.0, np.maximum(n - x, 1e-300), 1.0 - a), 1.0)
    empty = n <= 0
    return np.where(empty, 0.0, lo), np.where(empty, 1.0, hi)


def difference_interval(ref_only, cand_only, n, alpha_each_side: float):
    """Conservative bounds (points) of the found-rate difference ``candidate - reference``
    (module docstring); each bound holds with error at most ``alpha_each_side`` for
    independent objects. Counts may be real (effective counts) and arrays (broadcast);
    scalars give a tuple of floats."""
    r, c, n = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (ref_only, cand_only, n)))
    m = r + c
    n = np.where(n > 0, np.maximum(n, m), n)  # more changes than objects (false positives)
    q_lo, q_hi = beta_bounds(m, n, alpha_each_side / 2)
    p_lo, p_hi = beta_bounds(c, m, alpha_each_side / 2)
    low = np.minimum(q_lo * (2 * p_lo - 1), q_hi * (2 * p_lo - 1))
    high = np.maximum(q_lo * (2 * p_hi - 1), q_hi * (2 * p_hi - 1))
    low, high = np.where(n > 0, 100.0 * low, -100.0), np.where(n > 0, 100.0 * high, 100.0)
    if low.ndim == 0:
        return float(low), float(high)
    return low, high


# ----------------------------------------------------------------------------- frames


def frame_sums(n_f, ref_f, cand_f) -> dict[str, np.ndarray]:
    """What :func:`clustered_interval` needs of per-frame counts ``(..., F)`` (leading axes:
    independent replicates, e.g. simulation runs): totals ``n``, ``ref_only``,
    ``cand_only``, the frames, the frames with a discordance, ``sum n_f^2`` and the
    cluster-robust sum of squares ``sum (d_f - delta n_f)^2`` with ``d_f = cand_f - ref_f``."""
    n_f, ref_f, cand_f = (np.asarray(v, np.float64) for v in (n_f, ref_f, cand_f))
    n = n_f.sum(-1)
    d_f = cand_f - ref_f
    delta = np.divide(d_f.sum(-1), n, out=np.zeros_like(n), where=n > 0)
    return {
        "n": n,
        "ref_only": ref_f.sum(-1),
        "cand_only": cand_f.sum(-1),
        "frames": np.full(n.shape, float(n_f.shape[-1])),
        "discordant_frames": np.sum((ref_f + cand_f) > 0, -1).astype(np.float64),
        "n_squared": np.sum(n_f**2, -1),
        "cluster_ss": np.sum((d_f - delta[..., None] * n_f) ** 2, -1),
    }


def design_effect(sums: dict) -> np.ndarray:
    """The design effect of the paired difference (module docstring): the estimated one when
    at least :data:`MIN_DISCORDANT_FRAMES` frames hold a discordance, else at least the worst
    case ``sum n_f^2 / sum n_f``; never below 1."""
    n, m = sums["n"], sums["ref_only"] + sums["cand_only"]
    frames = sums["frames"]
    with np.errstate(invalid="ignore", divide="ignore"):
        delta = (sums["cand_only"] - sums["ref_only"]) / n
        v_cluster = frames / np.maximum(frames - 1, 1) * sums["cluster_ss"] / n**2
        v_objects = (m / n - delta**2) / n
        estimated = np.where(v_objects > 0, v_cluster / v_objects, 1.0)
        worst = sums["n_squared"] / n
    estimated = np.nan_to_num(estimated, nan=1.0)
    worst = np.nan_to_num(worst, nan=1.0)
    few = sums["discordant_frames"] < MIN_DISCORDANT_FRAMES
    return np.maximum(1.0, np.where(few, np.maximum(estimated, worst), estimated))


def clustered_interval(sums: dict, alpha_each_side: float):
    """Bounds (points) of the difference with frames as the unit: the conservative interval
    of the counts divided by :func:`design_effect`. Returns ``(lo, hi, deff)`` (arrays over
    the leading axes of ``sums``, floats for scalars)."""
    deff = design_effect(sums)
    lo, hi = difference_interval(
        sums["ref_only"] / deff, sums["cand_only"] / deff, sums["n"] / deff, alpha_each_side
    )
    if np.ndim(deff) == 0:
        return float(lo), float(hi), float(deff)
    return lo, hi, deff


# ----------------------------------------------------------------------------- tests, tables


def mcnemar_p(ref_only: int, cand_only: int) -> float:
    """Exact two-sided McNemar p-value (binomial test of the discordant objects at 1/2)."""
    m = ref_only + cand_only
    if m == 0:
        return 1.0
    return min(1.0, 2.0 * binom_cdf(min(ref_only, cand_only), m, 0.5))


def holm(p_values: Sequence[float]) -> list[float]:
    """Holm step-down adjusted p-values (same order)."""
    order = np.argsort(p_values)
    k = len(p_values)
    adjusted, running = [0.0] * k, 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (k - rank) * p_values[i]))
        adjusted[i] = running
    return adjusted


def paired_table(
    ref: np.ndarray, cand: np.ndarray, frame: np.ndarray | None = None, frames: int = 0
) -> dict:
    """The 2x2 table of paired outcomes (same objects, same order); with ``frame`` (the
    frame index of each object) also the per-frame counts ``frame_n``, ``frame_ref_only``,
    ``frame_cand_only`` (arrays over at least ``frames`` frames)."""
    ref, cand = np.asarray(ref, bool), np.asarray(cand, bool)
    if ref.shape != cand.shape:
        raise ValueError(f"paired outcomes need the same objects: {ref.shape} vs {cand.shape}")
    out = {
        "n": int(ref.size),
        "both": int(np.sum(ref & cand)),
        "ref_only": int(np.sum(ref & ~cand)),
        "cand_only": int(np.sum(~ref & cand)),
        "neither": int(np.sum(~ref & ~cand)),
    }
    if frame is not None:
        frame = np.asarray(frame, np.int64)
        size = max(frames, int(frame.max()) + 1 if frame.size else 0)
        out["frame_n"] = np.bincount(frame, minlength=size)
        out["frame_ref_only"] = np.bincount(frame, ref & ~cand, minlength=size)
        out["frame_cand_only"] = np.bincount(frame, ~ref & cand, minlength=size)
    return out


def table_sums(table: dict) -> dict:
    """:func:`frame_sums` of a table with per-frame counts; one frame per object without."""
    if "frame_n" in table:
        return frame_sums(table["frame_n"], table["frame_ref_only"], table["frame_cand_only"])
    n, r, c = table["n"], table["ref_only"], table["cand_only"]
    ref_f = np.r_[np.ones(r), np.zeros(n - r)]
    cand_f = np.r_[np.zeros(r), np.ones(c), np.zeros(n - r - c)]
    return frame_sums(np.ones(n), ref_f, cand_f)
