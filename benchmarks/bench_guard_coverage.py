"""Coverage of the guard's AP intervals (paired frame bootstrap, ``diff -+ z se``) by simulation.

A population of generated KITTI-like frames (``bench_kitti_eval.generate_dataset``: cars,
vans, pedestrians, cyclists, DontCare; perturbed true positives, misses, confusions, false
positives) is scored by a reference and a candidate (the reference's detections moved a
little, each frame by a shared offset as a quantization error would, and re-scored). The
"true" AP differences are those on the whole population. Guard sets of ``--frames`` frames
are drawn from it (without replacement); each gets the guard's paired bootstrap
(:func:`gac_jax.guard.ap_bootstrap.paired_ap_bootstrap`) and its interval at
``--level`` (two-sided). Printed: per AP entry the share of sets whose interval holds the
population's difference (the coverage), the median interval half-width, and the worst
entries.

    python benchmarks/bench_guard_coverage.py [--population 12000] [--frames 500] [--sets 100]
        [--resamples 100] [--level 0.90] [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np
from scipy.special import ndtri

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_kitti_eval import generate_dataset  # noqa: E402  (benchmarks/ is on sys.path)
from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.guard.ap_bootstrap import paired_ap_bootstrap  # noqa: E402


def candidate_run(dts, seed: int, shift_m: float = 0.05, score_sd: float = 0.02):
    """The reference's detections moved (a per-frame shared offset plus per-object noise,
    ``shift_m`` metres each) and re-scored (``score_sd``)."""
    rng = np.random.default_rng(seed)
    out = []
    for d in dts:
        n = len(d)
        move = rng.normal(0, shift_m, (1, 3)) + rng.normal(0, shift_m, (n, 3))
        score = np.clip(d.score + rng.normal(0, score_sd, n), 1e-3, 1.0)
        out.append(dataclasses.replace(d, location=d.location + move, score=score))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--population", type=int, default=12000)
    p.add_argument("--frames", type=int, default=500)
    p.add_argument("--sets", type=int, default=100)
    p.add_argument("--resamples", type=int, default=100)
    p.add_argument("--level", type=float, default=0.90)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    print(one_line(describe_machine("numpy", "scipy")))
    gts, ref = generate_dataset(args.population, args.seed)
    cand = candidate_run(ref, args.seed + 1)
    t0 = time.perf_counter()
    truth = paired_ap_bootstrap(gts, ref, cand, resamples=2)
    print(f"population {args.population} frames scored in {time.perf_counter() - t0:.1f} s")
    z = float(ndtri(0.5 + args.level / 2))
    rng = np.random.default_rng(args.seed + 2)
    hits = {k: 0 for k in truth}
    hits_bc = {k: 0 for k in truth}
    half = {k: [] for k in truth}
    t0 = time.perf_counter()
    for _ in range(args.sets):
        pick = rng.choice(args.population, args.frames, replace=False)
        result = paired_ap_bootstrap(
            [gts[i] for i in pick],
            [ref[i] for i in pick],
            [cand[i] for i in pick],
            resamples=args.resamples,
            seed=int(rng.integers(1 << 31)),
        )
        for k, row in result.items():
            hits[k] += abs(row["diff"] - truth[k]["diff"]) <= z * row["se"]
            hits_bc[k] += abs(row["diff"] - row["bias"] - truth[k]["diff"]) <= z * row["se"]
            half[k].append(z * row["se"])
    per_set = (time.perf_counter() - t0) / args.sets
    coverage = {k: hits[k] / args.sets for k in truth}
    corrected = {k: hits_bc[k] / args.sets for k in truth}
    se = np.sqrt(args.level * (1 - args.level) / args.sets)
    print(
        f"{args.sets} sets of {args.frames} frames, {args.resamples} resamples each "
        f"({per_set:.1f} s per set); nominal {args.level:.2f}, simulation se {se:.3f}"
    )
    print(
        f"{'entry':32s}{'true diff':>10s}{'coverage':>10s}{'bias-corrected':>15s}"
        f"{'median half-width':>19s}"
    )
    for k in sorted(truth, key=coverage.get):
        print(
            f"{k:32s}{truth[k]['diff']:+10.2f}{coverage[k]:10.2f}{corrected[k]:15.2f}"
            f"{np.median(half[k]):19.2f}"
        )
    for name, cov in (("diff -+ z se", coverage), ("bias-corrected", corrected)):
        values = np.array(list(cov.values()))
        print(
            f"{name}: coverage over {len(values)} entries: median {np.median(values):.2f}, "
            f"min {values.min():.2f}, mean {values.mean():.2f}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
