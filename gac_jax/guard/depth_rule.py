"""Paired per-frame accuracy guard of the depth network: float32 vs a candidate precision.

KITTI's depth metrics are means of per-image values (:mod:`gac_jax.evaluation.depth_metrics`),
so the difference of two runs on the same images is the mean of the per-image differences:
an additive, non-stepping quantity whose sampling error a paired interval states exactly
(unlike AP, see :mod:`gac_jax.guard.detector_rule`). Both runs are scored on the same
frames. The unit is the *frame*: the left and right images of a frame see the same scene and
their errors are correlated, so each frame contributes the mean over its images of
``candidate - reference``, and the interval is Student's t over the frames.

The guard takes at least :data:`MIN_FRAMES` frames (fewer are refused: with a skewed
per-frame difference, a few frames carrying a large change, a t interval on a handful of
frames says "within" far too often) and :func:`spread_frames` picks them evenly across the
drives in (drive, frame) order rather than the first N, which on KITTI are consecutive,
strongly correlated frames of one or two drives.

The rule (``margin`` default 0.2 SILog points, ``alpha`` default 0.05), on SILog (the KITTI
benchmark's ranking metric), at look ``k`` (the k-th guard run of this model and candidate,
``alpha_k = alpha / 2^k``: all looks together spend at most ``alpha``, as
:func:`~gac_jax.guard.paired_proportions.look_alpha`):

* **within**: the interval of the mean SILog difference at ``1 - 2 alpha_k`` (each side at
  ``alpha_k``: two one-sided tests) lies inside ``[-margin, +margin]``.
* **beyond**: its interval at ``1 - alpha_k`` lies entirely outside (the verdict says which
  way and by how much).
* **undecided** otherwise: the frames are too few; :func:`frames_needed` says how many would
  decide if the observed mean and spread held.

Also reported, not deciding: the same paired mean and interval for absRel, sqRel, iRMSE,
RMSE and delta<1.25 (their own units), so a user sees what moved.

Pure numpy (and scipy's Student t, a JAX dependency); no JAX.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy.special import stdtrit

from gac_jax.guard.paired_proportions import look_alpha

MARGIN = 0.2  # SILog points (100 log m)
ALPHA = 0.05
MIN_FRAMES = 100
DECIDING = "silog"
REPORTED = ("silog", "abs_rel", "sq_rel", "irmse", "rmse", "delta1")


def frame_differences(
    ref: Sequence[dict], cand: Sequence[dict], metrics: Sequence[str] = REPORTED
) -> tuple[list[str], np.ndarray]:
    """Per-frame paired differences ``candidate - reference``.

    Args:
      ref, cand: per-image rows ``{'frame', 'camera', metric: value, ...}`` (the depth
        evaluator's ``per_image``) of the same images, in any order.
      metrics: the metric keys to difference.
    Returns:
      ``(frames, diffs)``: frame ids in first-seen order of ``ref`` and a (F, len(metrics))
      float64 array, each row the mean over the frame's images.
    Raises:
      ValueError: the two runs scored different images (naming one).
    """
    cand_by_key = {(r["frame"], int(r["camera"])): r for r in cand}
    ref_keys = {(r["frame"], int(r["camera"])) for r in ref}
    if len(ref_keys) != len(ref) or len(cand_by_key) != len(cand):
        raise ValueError("an image is scored twice in one run")
    missing = sorted(ref_keys ^ set(cand_by_key))
    if missing:
        frame, camera = missing[0]
        raise ValueError(
            f"the runs scored different images ({len(missing)}; e.g. {frame} camera {camera})"
        )
    sums: dict[str, np.ndarray] = {}
    counts: dict[str, int] = {}
    for r in ref:
        c = cand_by_key[(r["frame"], int(r["camera"]))]
        d = np.array([float(c[m]) - float(r[m]) for m in metrics], dtype=np.float64)
        sums[r["frame"]] = sums.get(r["frame"], 0.0) + d
        counts[r["frame"]] = counts.get(r["frame"], 0) + 1
    frames = list(sums)
    diffs = np.array([sums[f] / counts[f] for f in frames], dtype=np.float64)
    return frames, diffs.reshape(len(frames), len(metrics))


def mean_interval(values: np.ndarray, alpha_each_side: float) -> tuple[float, float, float]:
    """``(mean, lo, hi)``: Student's t interval of the mean of ``values`` (n,) with
    ``alpha_each_side`` on each side; infinite bounds for fewer than 2 values."""
    values = np.asarray(values, dtype=np.float64)
    n = values.size
    if n == 0:
        return 0.0, -math.inf, math.inf
    mean = float(values.mean())
    if n < 2:
        return mean, -math.inf, math.inf
    half = float(stdtrit(n - 1, 1.0 - alpha_each_side)) * float(values.std(ddof=1)) / math.sqrt(n)
    return mean, mean - half, mean + half


def frames_needed(
    mean: float, sd: float, margin: float, alpha_each_side: float, limit: int = 10_000_000
) -> int | None:
    """The fewest frames at which the interval (``alpha_each_side``) of a mean ``mean`` with
    per-frame spread ``sd`` would lie inside ``+-margin`` (``|mean| < margin``) or outside it;
    None when ``|mean| == margin`` or more than ``limit`` frames would be needed."""
    gap = margin - abs(mean) if abs(mean) < margin else abs(mean) - margin
    if gap <= 0:
        return None
    if sd == 0:
        return 2

    def decided(k: int) -> bool:
        return float(stdtrit(k - 1, 1.0 - alpha_each_side)) * sd / math.sqrt(k) < gap

    lo, hi = 2, 2
    while not decided(hi):
        lo, hi = hi, hi * 2
        if hi > limit:
            return None
    while hi - lo > 1:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if decided(mid) else (mid, hi)
    return hi


def drive_of(frame_id: str) -> str:
    """The drive (sequence) of a frame id: ``'<drive>/<frame>'`` -> ``<drive>``; a
    ``depth_selection`` name ``<drive>_image_<frame>_image_0<c>`` -> ``<drive>``."""
    if "/" in frame_id:
        return frame_id.rsplit("/", 1)[0]
    return frame_id.split("_image_", 1)[0]


def spread_frames(frame_ids: Sequence[str], n: int) -> list[str]:
    """``n`` distinct frame ids spread evenly over all drives: the ids sorted by (drive,
    frame), then every ``len / n``-th (deterministic; each drive gets its share, and frames
    of one drive are as far apart as the share allows). All of them when ``n`` is at least
    their number."""
    unique = sorted(set(frame_ids), key=lambda f: (drive_of(f), f))
    if n >= len(unique):
        return unique
    picks = np.floor((np.arange(n) + 0.5) * len(unique) / n).astype(np.int64)
    return [unique[i] for i in picks]


def sample_source(source, frame_ids: Sequence[str]):
    """A shallow copy of a depth source restricted to the images of ``frame_ids`` (both
    cameras, the source's order kept): KITTI-depth folders (``frames``) and
    ``depth_selection`` folders (``items``)."""
    import copy

    keep = set(frame_ids)
    out = copy.copy(source)
    if getattr(source, "frames", None) is not None:
        out.frames = [f for f in source.frames if f.frame_id in keep]
    elif getattr(source, "items", None) is not None:
        out.items = [it for it in source.items if it.name in keep]
    else:
        raise ValueError("this depth source cannot be sampled (a KITTI-depth folder can)")
    return out


def source_frame_ids(source) -> list[str]:
    """The frame ids of a depth source (KITTI-depth folder or ``depth_selection``)."""
    if getattr(source, "frames", None) is not None:
        return [f.frame_id for f in source.frames]
    if getattr(source, "items", None) is not None:
        return [it.name for it in source.items]
    raise ValueError("this depth source cannot list its frames (a KITTI-depth folder can)")


def decide_depth(
    ref: Sequence[dict],
    cand: Sequence[dict],
    margin: float = MARGIN,
    alpha: float = ALPHA,
    look: int = 1,
    min_frames: int = MIN_FRAMES,
) -> dict:
    """The rule of the module docstring.

    Args:
      ref, cand: per-image metric rows of float32 and of the candidate (same images).
      look: which guard run of this model and candidate this is (1, 2, ...).
    Raises:
      ValueError: fewer than ``min_frames`` frames, or the runs scored different images.
    Returns:
      ``{'verdict': 'within'|'beyond'|'undecided', 'reason': one line, 'margin', 'alpha',
      'frames', 'images', 'deciding': 'silog', 'frames_needed' (undecided only),
      'reference': {metric: mean}, 'candidate': {metric: mean}, 'criteria': {'silog': {'n',
      'diff', 'sd', 'within_interval', 'beyond_interval', 'status'}}, 'reported': {metric:
      {'diff', 'interval'}}}`` (differences candidate - reference in each metric's unit;
      ``interval`` at ``1 - 2 alpha_k``).
    """
    frames, diffs = frame_differences(ref, cand, REPORTED)
    n = len(frames)
    if n < min_frames:
        raise ValueError(
            f"the depth guard needs at least {min_frames} frames spread over the drives, got {n}"
        )
    a = look_alpha(alpha, look)
    column = diffs[:, REPORTED.index(DECIDING)] if n else np.zeros(0)
    mean, w_lo, w_hi = mean_interval(column, a)
    _, b_lo, b_hi = mean_interval(column, a / 2)
    sd = float(column.std(ddof=1)) if n > 1 else None
    if b_lo > margin or b_hi < -margin:
        status = "beyond"
    elif -margin <= w_lo and w_hi <= margin:
        status = "within"
    else:
        status = "undecided"
    row = {
        "n": n,
        "diff": mean,
        "sd": sd,
        "within_interval": [w_lo, w_hi],
        "beyond_interval": [b_lo, b_hi],
        "status": status,
    }
    reported = {}
    for j, m in enumerate(REPORTED):
        d, lo, hi = mean_interval(diffs[:, j] if n else np.zeros(0), a)
        reported[m] = {"diff": d, "interval": [lo, hi]}
    out = {
        "margin": margin,
        "alpha": alpha,
        "look": look,
        "alpha_look": a,
        "frames": n,
        "images": len(ref),
        "deciding": DECIDING,
        "reference": {m: float(np.mean([r[m] for r in ref])) if ref else None for m in REPORTED},
        "candidate": {m: float(np.mean([r[m] for r in cand])) if cand else None for m in REPORTED},
        "criteria": {DECIDING: row},
        "reported": reported,
    }
    if status == "beyond":
        way = "up (worse)" if mean > 0 else "down (better)"
        out |= {
            "verdict": "beyond",
            "reason": f"SILog moved {way} beyond {margin}: {mean:+.3f} [{b_lo:+.3f}, "
            f"{b_hi:+.3f}] on {n} frames",
        }
    elif status == "within":
        out |= {
            "verdict": "within",
            "reason": f"SILog within {margin}: {mean:+.3f} [{w_lo:+.3f}, {w_hi:+.3f}] on "
            f"{n} frames",
        }
    else:
        a_next = look_alpha(alpha, look + 1)
        side = a_next if abs(mean) < margin else a_next / 2
        need = frames_needed(mean, sd, margin, side) if sd is not None else None
        need = None if need is None else max(need, min_frames)
        needed_text = (
            f"about {need} frames would decide it at look {look + 1}"
            if need is not None
            else "no affordable number of frames would decide it at the observed spread"
            if sd is not None
            else "at least 2 frames are needed"
        )
        out |= {
            "verdict": "undecided",
            "frames_needed": need,
            "reason": f"too few frames: SILog {mean:+.3f} [{w_lo:+.3f}, {w_hi:+.3f}] on {n} "
            f"frames; {needed_text}",
        }
    return out
