"""Frames the guard's count criteria need to say "within": the current rule (tests by betting
within per-frame bounds, ``gac_jax.guard.frame_betting``) against the earlier one (a
design effect estimated from the frames, ``paired_proportions.clustered_interval``), by
simulation.

Guard sets are drawn with per-frame statistics shaped like the default detector's on generated
frames (docs/results.md, "Runtimes and precisions"): the Car objects of a frame at each
difficulty are a binomial share of the 3-8 cars the generator places plus 0-2 far ones,
1.28 / 2.35 / 2.65 per frame on average (5,135 / 9,395 / 10,607 on 4,000 frames). Recall rows:
each object flips at the IoU boundary with a chance split evenly between lost and gained
(``--flips``; the results page: about 1-2 % of the objects, bf16 about 1 %, int8 about 2 %).
False-positive rows: each frame gains or loses one false positive with a chance split evenly
(``--fp-changes``, per frame; bf16 about 3 % of the easy objects in all, 0.04 per frame, int8
about 8 % of the moderate ones, 0.19 per frame). OpenVINO float32 found exactly float32's
objects: no change at all. ``--shift`` points of true change (losses,
false positives gained) on top. For every row and rule: the fewest frames of a grid growing
by 10 % at which at least ``--share`` of ``--sets`` guard sets say within at look 1 (alpha
0.025 each side; the same sets for both rules). A verdict needs every row within: the last
line is the largest row per precision (f32: OpenVINO float32).

    python benchmarks/bench_guard_power.py [--sets 40] [--share 0.5] [--shift 0] [--fp-cap 20]
        [--flips 0,0.01,0.02] [--fp-changes 0,0.04,0.19] [--seed 0]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine_info import describe_machine, one_line  # noqa: E402  (benchmarks/ is on sys.path)

from gac_jax.guard import frame_betting as fb  # noqa: E402
from gac_jax.guard import paired_proportions as pp  # noqa: E402

MARGIN, ALPHA_SIDE = 0.5, 0.025  # points; look 1 of alpha 0.05
OBJECTS = {"easy": 1.28, "moderate": 2.35, "hard": 2.65}  # Car objects per frame (4,000 frames)
PLACED = 5.5 + 1.0  # mean cars the generator places: 3-8 near, 0-2 far
LARGEST = 400_000  # frames: beyond this the search stops


def draw(rng, sets: int, frames: int, difficulty: str, kind: str, rate: float, shift: float):
    """``(n, lost, gained)`` (sets, frames) of one row (module docstring)."""
    placed = rng.integers(3, 9, (sets, frames)) + rng.integers(0, 3, (sets, frames))
    n = rng.binomial(placed, OBJECTS[difficulty] / PLACED).astype(np.float64)
    if rate == 0 and shift == 0:
        return n, np.zeros_like(n), np.zeros_like(n)
    if kind == "recall":
        flips = rng.binomial(n.astype(np.int64), rate + shift / 100)
        lost = rng.binomial(flips, (rate / 2 + shift / 100) / (rate + shift / 100))
        return n, lost.astype(np.float64), (flips - lost).astype(np.float64)
    u = rng.random((sets, frames))
    up = rate / 2 + shift / 100 * OBJECTS[difficulty]
    return n, (u >= 1 - rate / 2).astype(np.float64), (u < up).astype(np.float64)


def within(rule: str, n, lost, gained, kind: str, fp_cap: float) -> np.ndarray:
    """(sets,) bool: the rule's verdict on each set's row."""
    if rule == "earlier":
        lo, hi, _ = pp.clustered_interval(pp.frame_sums(n, lost, gained), ALPHA_SIDE)
        return (lo >= -MARGIN) & (hi <= MARGIN)
    bounds = fb.FrameBounds(kind, n.max(-1), fp_cap)
    return fb.within_margin(gained - lost, n, MARGIN, bounds, ALPHA_SIDE)


def frames_needed(rng, args, difficulty, kind, rate) -> dict[str, int | None]:
    """The fewest frames of the grid at which ``--share`` of the sets say within, per rule."""
    found: dict[str, int | None] = {"earlier": None, "current": None}
    frames = 500
    while frames <= LARGEST and None in found.values():
        n, lost, gained = draw(rng, args.sets, frames, difficulty, kind, rate, args.shift)
        for rule in found:
            if found[rule] is None:
                share = within(rule, n, lost, gained, kind, args.fp_cap).mean()
                found[rule] = frames if share >= args.share else None
        frames = int(frames * 1.1)
    return found


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sets", type=int, default=40)
    p.add_argument("--share", type=float, default=0.5)
    p.add_argument("--shift", type=float, default=0.0, help="true change, points")
    p.add_argument("--fp-cap", type=float, default=fb.FP_CAP)
    p.add_argument("--flips", default="0,0.01,0.02", help="f32,bf16,int8: objects flipping")
    p.add_argument("--fp-changes", default="0,0.04,0.19", help="f32,bf16,int8: per frame")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    flips = [float(v) for v in args.flips.split(",")]
    fp_changes = [float(v) for v in args.fp_changes.split(",")]
    print(one_line(describe_machine("numpy", "scipy")))
    print(
        f"{args.sets} guard sets per frame count, within in at least {args.share:.0%} of them; "
        f"margin {MARGIN} points, alpha {ALPHA_SIDE} each side (look 1); true change "
        f"{args.shift:+.2f} points; false-positive cap {args.fp_cap:g} per frame"
    )
    rng = np.random.default_rng(args.seed)
    print(f"{'precision':10s}{'row':28s}{'changes':>20s}{'earlier rule':>14s}{'now':>10s}")
    t0 = time.perf_counter()
    for name, flip, fp in zip(("f32", "bf16", "int8"), flips, fp_changes, strict=True):
        worst = {"earlier": 0, "current": 0}
        for difficulty in OBJECTS:
            for kind, rate, what in (
                ("recall", flip, f"{flip:.0%} of objects"),
                ("fp", fp, f"{fp:.2f} per frame"),
            ):
                need = frames_needed(rng, args, difficulty, kind, rate)
                cells = [f"{v:,}" if v else f"> {LARGEST:,}" for v in need.values()]
                row = f"Car {difficulty} {'recall' if kind == 'recall' else 'false positives'}"
                print(f"{name:10s}{row:28s}{what:>20s}{cells[0]:>14s}{cells[1]:>10s}", flush=True)
                for rule, v in need.items():
                    worst[rule] = max(worst[rule], v or LARGEST + 1)
        cells = [f"{v:,}" if v <= LARGEST else f"> {LARGEST:,}" for v in worst.values()]
        print(f"{name:10s}{'verdict (the largest row)':28s}{'':>20s}{cells[0]:>14s}{cells[1]:>10s}")
    print(f"({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
