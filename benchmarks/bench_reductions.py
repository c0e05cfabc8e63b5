"""The train step's reductions: the formulations XLA:CPU runs fast against the plain jnp ones.

Two cases, both called alternately with the plain formulation, medians of wall and
process-CPU milliseconds (CPU time is the steadier figure on a shared machine), and the
largest difference to a float64 numpy reference:

* BatchNorm's per-channel sums (``sum(x)`` and ``sum(x * y)`` over all axes but the last) at
  the activation shapes of the default detector (batch 8, 160x720, trunk width 32) and of the
  paper depth net's largest decoder stage: ``jnp.sum`` (XLA rewrites it into a ``reduce-window``
  plus a reduce) vs :func:`gac_jax.models.batch_norm._channel_sums` (a tree of variadic
  reductions over blocks of at most 32 rows).
* the anchor assignment's argmax over the ground truth of the (8, 14400, 32) IoU matrix (the
  default detector, 32 padded objects): ``jnp.argmax`` (a variadic value/index reduction) vs
  :func:`gac_jax.detection.assignment.first_argmax` (max, then the smallest index equal to it).

    python benchmarks/bench_reductions.py [--repeats 21]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from machine_info import describe_machine, one_line  # noqa: E402

from gac_jax.detection.assignment import box_iou, first_argmax  # noqa: E402
from gac_jax.models.batch_norm import _channel_sums  # noqa: E402

SUM_SHAPES = {
    "stem 8x80x360x32": (8, 80, 360, 32),
    "layer1 8x40x180x32": (8, 40, 180, 32),
    "layer2 8x20x90x64": (8, 20, 90, 64),
    "layer3 8x10x45x128": (8, 10, 45, 128),
    "depth decoder 1x176x608x64": (1, 176, 608, 64),
}


def _time(fn, *args) -> tuple[float, float]:
    t0, c0 = time.perf_counter(), time.process_time()
    jax.block_until_ready(fn(*args))
    return (time.perf_counter() - t0) * 1e3, (time.process_time() - c0) * 1e3


def _compare(cases: dict, args: tuple, repeats: int) -> dict:
    """Alternating calls of each jitted case; medians of wall and CPU ms."""
    fns = {name: jax.jit(fn) for name, fn in cases.items()}
    outs = {name: jax.block_until_ready(fn(*args)) for name, fn in fns.items()}  # compile
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            times[name].append(_time(fn, *args))
    result = {}
    for name, ts in times.items():
        result[name] = {
            "wall_ms": round(statistics.median(t[0] for t in ts), 2),
            "cpu_ms": round(statistics.median(t[1] for t in ts), 2),
        }
    return result, outs


def channel_sums(repeats: int) -> dict:
    rows = {}
    for label, shape in SUM_SHAPES.items():
        rng = np.random.default_rng(0)
        a = (1.0 + 2.0 * rng.standard_normal(shape)).astype(np.float32)
        b = rng.standard_normal(shape).astype(np.float32)
        axes = tuple(range(len(shape) - 1))
        cases = {
            "jnp.sum": lambda a, b, axes=axes: (jnp.sum(a, axes), jnp.sum(a * b, axes)),
            "channel_sums": lambda a, b: _channel_sums(a, a * b),
        }
        result, outs = _compare(cases, (jnp.asarray(a), jnp.asarray(b)), repeats)
        a64, b64 = a.astype(np.float64), b.astype(np.float64)
        ref = (a64.sum(axes), (a64 * b64).sum(axes))
        for name, out in outs.items():
            pairs = zip(out, ref, strict=True)
            err = max(float(np.max(np.abs(o - r) / np.max(np.abs(r)))) for o, r in pairs)
            result[name]["max_rel_error_vs_float64"] = float(f"{err:.2g}")
        result["speedup_wall"] = round(
            result["jnp.sum"]["wall_ms"] / result["channel_sums"]["wall_ms"], 2
        )
        rows[label] = result
        print(label, json.dumps(result), flush=True)
    return rows


def argmax(repeats: int) -> dict:
    rng = np.random.default_rng(0)
    corner = rng.uniform(0, 700, (14400, 2))
    anchors = np.concatenate([corner, corner + rng.uniform(10, 100, corner.shape)], -1)
    corner = rng.uniform(0, 700, (8, 32, 2))
    gt = np.concatenate([corner, corner + rng.uniform(10, 100, corner.shape)], -1)
    args = (jnp.asarray(anchors, jnp.float32), jnp.asarray(gt, jnp.float32))

    def iou(anchors, gt):
        return box_iou(anchors[None], gt)  # (8, 14400, 32)

    cases = {
        "jnp.argmax": lambda a, g: jnp.argmax(iou(a, g), -1).astype(jnp.int32),
        "first_argmax": lambda a, g: first_argmax(iou(a, g), jnp.max(iou(a, g), -1)),
    }
    result, outs = _compare(cases, args, repeats)
    result["identical"] = bool(np.array_equal(outs["jnp.argmax"], outs["first_argmax"]))
    result["speedup_wall"] = round(
        result["jnp.argmax"]["wall_ms"] / result["first_argmax"]["wall_ms"], 2
    )
    print("argmax (8, 14400, 32)", json.dumps(result), flush=True)
    return result


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("--repeats", type=int, default=21)
    p.add_argument("--json", help="write the results here")
    args = p.parse_args()
    machine = describe_machine("numpy", "jax")
    print(one_line(machine), flush=True)
    results = {
        "machine": machine,
        "channel_sums": channel_sums(args.repeats),
        "argmax": argmax(args.repeats),
    }
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
