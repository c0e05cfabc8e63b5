"""Bounds for a paired count difference with the frame as the unit, by betting: valid for any
per-frame distribution of the changes within stated per-frame bounds.

The guard's count criteria (:mod:`gac_jax.guard.criteria`) give per frame ``f``
its evaluated objects ``n_f`` and the candidate's paired change ``d_f``: objects it found that
the reference missed minus the reverse (recall rows), or false positives gained minus lost
(false-positive rows). The difference bounded is ``delta = E[d] / E[n]`` over frames like the
guard frames (in points, ``100 delta``: found-rate, or false positives per 100 objects),
estimated by ``sum d_f / sum n_f``. Arrays are ``(..., F)``: frames last, any leading axes
(independent replicates, e.g. simulation runs).

**The test** of "delta > x" (null hypothesis ``delta <= x``) bets on ``X_f = d_f - x n_f``,
whose mean is at most 0 under the null: the capital starts at 1 and frame ``t`` multiplies it
by ``1 + lam_t X_t``, where ``lam_t >= 0`` is chosen from the frames before ``t`` only. For
independent frames the capital is then a nonnegative supermartingale under the null, and by
Ville's inequality it ever reaches ``1 / a`` with probability at most ``a``, **whatever the
distribution of the changes**: rare bursts, losses only in crowded frames, changes tied to
frame size, whole frames lost. The one condition is that the capital cannot turn negative:
``lam_t <= 1 / L`` where ``X_f >= -L`` for every frame that can occur (the bounds below). The
test says "delta > x" when the capital reaches ``1 / a`` at some frame; "delta < x" is the
same test of ``-d`` at ``-x``. (The earlier rule, a design effect estimated from the guard
frames, cannot see a burst that the guard frames happen not to hold: below 30 changed frames
it took an average frame size as the worst case, above them the background's design effect.)

**The bounds: what the guarantee assumes.**

* Recall rows (found objects, heading, error quantiles): a frame changes at most all its
  objects, ``|d_f| <= n_f``, and ``n_f <= B``, the largest evaluated-object count of a guard
  frame (of the class and difficulty), so ``L = (1 + x) B``. This assumes no frame like the
  guard frames holds more evaluated objects than the largest guard frame; a new frame exceeds
  the largest of ``N`` exchangeable ones with probability at most ``1 / (N + 1)``.
* False-positive rows: ``|d_f| <= cap`` (:data:`FP_CAP` per frame, the guard's ``--fp-cap``),
  so ``L = cap + max(x, 0) B``: an assumption about the candidate that the guard checks on the
  guard frames. A frame beyond it breaks the side of the test it would need (more false
  positives than the cap gained: the "no more false positives" side; lost: the other), which
  then never rejects, and the criterion stays undecided, saying so.

**The bets** (the predictable plug-in of Waudby-Smith and Ramdas, "Estimating means of bounded
random variables by betting", JRSS B 2024, for a fixed number of frames ``N``):
``lam_t = min(c / L, sqrt(2 log(1 / a) / (N v_t)))``, ``c`` = :data:`BET_LIMIT`, ``v_t`` the
mean square of ``d_s - r_s n_s`` over the frames before ``t`` (``r_s`` the running ratio
``sum d / sum n`` up to ``s``) with :data:`PRIOR_VARIANCE` counted as one frame. The bets set
the power only, never the level.

**What it costs.** A frame may hide up to ``L`` objects, so agreement on every frame decides
"within" only after ``log(1 / a) / log(1 + c m n / L)`` frames (``m`` the margin as a share,
``n`` the mean objects per frame): a burst as large as the bound, as rare as ``log(1/a) / N``,
would otherwise go unseen. With changes seen, the capital grows about as a z-test's statistic
with ``sqrt(2 log(1 / a))`` in place of ``z``.

**Intervals** (:func:`interval`): the lower bound is the largest ``x`` whose "delta > x" test
rejects, the upper the smallest ``x`` whose "delta < x" test rejects (grid refinement; each
search starts from the side of the point given, so the interval agrees with the tests at the
margins that decide).

Pure numpy; no JAX.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

BET_LIMIT = 0.95  # c: a bet risks at most this share of the capital on one frame
PRIOR_VARIANCE = 0.25  # objects^2, counted as one frame of the running mean square
FP_CAP = 20  # false positives one frame may gain or lose (the guard's --fp-cap)
FRAMES_LIMIT = 2_000_000  # frames_to_reject: beyond this, no affordable number of frames
_GRID = 33  # interval search: points per refinement round
_TOLERANCE = 1e-6  # interval search: bracket width (as a share; 1e-4 points)


@dataclasses.dataclass(frozen=True)
class FrameBounds:
    """What one frame's change can be.

    ``kind``: ``'recall'`` (``|d_f| <= n_f <= n_max``) or ``'fp'`` (``|d_f| <= cap``);
    ``n_max``: the largest evaluated-object count of a frame (scalar or ``(...,)``, one per
    replicate); ``cap``: false positives per frame (``'fp'`` only).
    """

    kind: str
    n_max: float | np.ndarray
    cap: float = FP_CAP

    def __post_init__(self):
        if self.kind not in ("recall", "fp"):
            raise ValueError(f"kind must be 'recall' or 'fp', got {self.kind!r}")
        if self.kind == "fp" and not self.cap > 0:
            raise ValueError(f"the false-positive cap must be positive, got {self.cap}")

    def loss(self, x) -> np.ndarray:
        """``L(x)``: ``d_f - x n_f >= -L`` for every frame the bounds allow (``x`` a share)."""
        n_max = np.asarray(self.n_max, np.float64)
        x = np.asarray(x, np.float64)
        if self.kind == "recall":
            return np.maximum(1.0 + x, 0.0) * n_max
        return self.cap + np.maximum(x, 0.0) * n_max

    def admissible(self, d: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Whether every frame respects the bound on the losing side (``-d_f``), the side a
        "delta > x" test needs: ``(...,)`` bool."""
        limit = n if self.kind == "recall" else self.cap
        return np.all(-d <= limit, axis=-1)

    def largest_ratio(self, frames: int, objects: float) -> float:
        """The largest ``|delta|`` frames like these can show (the interval search's range)."""
        if self.kind == "recall":
            return 1.0
        return self.cap * frames / max(objects, 1.0)


def bet_scale(d: np.ndarray, n: np.ndarray, horizon: int | None = None) -> np.ndarray:
    """``1 / sqrt(N v_t)`` per frame ``(..., F)`` (module docstring; ``N`` = ``horizon``,
    default the frames): the bets before their level factor and limit. Frame ``t`` uses the
    frames before it only."""
    frames = d.shape[-1]
    horizon = frames if horizon is None else horizon
    cd, cn = np.cumsum(d, -1), np.cumsum(n, -1)
    ratio = np.divide(cd, cn, out=np.zeros_like(cd), where=cn > 0)
    square = (d - ratio * n) ** 2
    before = np.concatenate([np.zeros(d.shape[:-1] + (1,)), np.cumsum(square, -1)[..., :-1]], -1)
    mean_square = (PRIOR_VARIANCE + before) / np.arange(1, frames + 1)
    return 1.0 / np.sqrt(horizon * mean_square)


def log_capital(d, n, x, bounds: FrameBounds, alpha: float, scale=None) -> np.ndarray:
    """The largest log capital over the frames of the "delta > x" bet (module docstring):
    ``(...,)`` for ``d, n`` ``(..., F)``; ``x`` broadcasts against the leading axes.
    ``scale``: :func:`bet_scale` of ``d, n`` (computed when None)."""
    d, n = np.asarray(d, np.float64), np.asarray(n, np.float64)
    scale = bet_scale(d, n) if scale is None else scale
    x = np.asarray(x, np.float64)[..., None]
    limit = BET_LIMIT / np.maximum(bounds.loss(x[..., 0]), 1e-12)[..., None]
    lam = np.minimum(math.sqrt(2.0 * math.log(1.0 / alpha)) * scale, limit)
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN where a frame breaks the bound
        steps = np.log1p(lam * (d - x * n))
    return np.max(np.cumsum(steps, -1), -1, initial=0.0)


def rejects(d, n, x, bounds: FrameBounds, alpha: float, scale=None) -> np.ndarray:
    """Whether the "delta > x" test rejects ``delta <= x`` at level ``alpha``: the capital
    reached ``1 / alpha`` and the frames respect the bound it needs. ``(...,)`` bool."""
    d, n = np.asarray(d, np.float64), np.asarray(n, np.float64)
    ok = bounds.admissible(d, n)
    return ok & (log_capital(d, n, x, bounds, alpha, scale) >= math.log(1.0 / alpha))


def within_margin(d, n, margin: float, bounds: FrameBounds, alpha: float) -> np.ndarray:
    """Whether both one-sided tests at ``alpha`` place ``delta`` inside ``+-margin`` points
    (two one-sided tests; ``(...,)`` bool). Each row's side nearer its margin is tested
    first, the other only where the first rejected (the same answer, less work)."""
    d, n = np.asarray(d, np.float64), np.asarray(n, np.float64)
    x = -margin / 100.0
    if d.ndim == 1:
        return bool(rejects(d, n, x, bounds, alpha) and rejects(-d, n, x, bounds, alpha))
    shape = d.shape[:-1]
    flat_d, flat_n = d.reshape(-1, d.shape[-1]), n.reshape(-1, n.shape[-1])
    n_max = np.broadcast_to(np.asarray(bounds.n_max, np.float64), shape).reshape(-1)
    nearer = np.where(flat_d.sum(-1) > 0, -1.0, 1.0)[:, None]  # gains: the upper side first
    out = np.zeros(len(flat_d), bool)
    rows = np.arange(len(flat_d))
    for sign in (nearer, -nearer):
        sub = dataclasses.replace(bounds, n_max=n_max[rows])
        passed = rejects(sign[rows] * flat_d[rows], flat_n[rows], x, sub, alpha)
        rows = rows[passed]
    out[rows] = True
    return out.reshape(shape)


def _largest_rejected(d, n, bounds: FrameBounds, alpha: float, point: float) -> float:
    """The largest ``x`` whose "delta > x" test rejects (one row, ``d, n`` ``(F,)``),
    searched above ``point`` if it rejects there, else below it."""
    scale = bet_scale(d, n)
    top = bounds.largest_ratio(len(d), float(n.sum()))
    if rejects(d, n, point, bounds, alpha, scale):
        lo, hi = point, max(top, point)
    else:
        lo, hi = min(-top, point), point
        if not rejects(d, n, lo, bounds, alpha, scale):
            return lo
    while hi - lo > _TOLERANCE:
        xs = np.linspace(lo, hi, _GRID)
        ok = rejects(np.broadcast_to(d, (_GRID, len(d))), n, xs, bounds, alpha, scale)
        ok[0] = True  # lo rejects (checked above or by the previous round)
        first_no = int(np.argmin(ok)) if not ok.all() else _GRID
        if first_no == _GRID:
            return hi
        lo, hi = xs[first_no - 1], xs[first_no]
    return lo


def interval(
    d, n, bounds: FrameBounds, alpha: float, around: tuple[float, float] = (0.0, 0.0)
) -> tuple[float, float]:
    """``(lo, hi)`` points: ``lo`` the largest difference the "delta > x" test rejects at
    ``alpha``, ``hi`` the smallest the "delta < x" test rejects (one row, ``d, n`` ``(F,)``).
    The searches start from ``around`` (points; lower, upper) on the side their test says,
    so ``lo >= around[0]`` exactly when "delta > around[0]" rejects, and ``hi <= around[1]``
    exactly when "delta < around[1]" does; ``-inf`` / ``+inf`` where the frames break the
    bound that side needs."""
    d, n = np.asarray(d, np.float64), np.asarray(n, np.float64)
    lo, hi = -math.inf, math.inf
    if bounds.admissible(d, n):
        lo = _largest_rejected(d, n, bounds, alpha, around[0] / 100.0)
    if bounds.admissible(-d, n):
        hi = -_largest_rejected(-d, n, bounds, alpha, -around[1] / 100.0)
    return float(100.0 * lo), float(100.0 * hi)


def _growth_frames(d, n, x: float, bounds: FrameBounds, alpha: float, limit: int) -> int | None:
    """A first estimate of :func:`frames_to_reject` (its early frames' smaller bets left out):
    the fewest ``N`` with ``N mean(log(1 + lam_N X)) >= log(1 / alpha)`` over the guard
    frames, ``lam_N`` the bet at ``N`` frames once the running mean square has settled; None
    beyond ``limit``."""
    ratio = d.sum() / n.sum() if n.sum() else 0.0
    spread = float(np.mean((d - ratio * n) ** 2))
    level = math.log(1.0 / alpha)
    cap = BET_LIMIT / max(float(bounds.loss(x)), 1e-12)
    steps = d - x * n

    def enough(frames: int) -> bool:
        bet = cap if spread == 0 else min(cap, math.sqrt(2.0 * level / (frames * spread)))
        with np.errstate(invalid="ignore"):
            return frames * float(np.mean(np.log1p(bet * steps))) >= level

    return _fewest(enough, 1, 2.0, limit)


def _fewest(holds, start: int, growth: float, limit: int, above: int = 0) -> int | None:
    """The fewest frames above ``above`` (to 1 %) for which ``holds(frames)`` (taken as
    monotone): from ``start``, growing by ``growth`` until it holds, then bisection; None
    beyond ``limit``."""
    lo, hi = above, max(start, above + 1)
    while not holds(hi):
        lo, hi = hi, int(hi * growth) + 1
        if hi > limit:
            return None
    while hi - lo > max(1, lo // 100):
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if holds(mid) else (mid, hi)
    return hi


def frames_to_reject(
    d, n, x: float, bounds: FrameBounds, alpha: float, limit: int = FRAMES_LIMIT
) -> int | None:
    """The fewest frames (more than ``F``, to 1 %) at which the "delta > x" test would reject
    at ``alpha`` if the guard frames ``d, n`` ``(F,)`` came again in the same order
    (repeated); None when the observed difference is not above ``x``, the frames break the
    bound, or more than ``limit`` frames would be needed. The search starts at an estimate
    from the frames' mean growth of the capital, then runs the test itself."""
    d, n = np.asarray(d, np.float64), np.asarray(n, np.float64)
    if not len(d) or not bounds.admissible(d, n) or d.sum() - x * n.sum() <= 0:
        return None
    guess = _growth_frames(d, n, x, bounds, alpha, 2 * limit)
    if guess is None:
        return None

    def decided(frames: int) -> bool:
        return bool(rejects(np.resize(d, frames), np.resize(n, frames), x, bounds, alpha))

    return _fewest(decided, int(0.9 * guess), 1.25, limit, above=len(d))
