"""The tracker's time per frame at 10, 50 and 100 objects (host CPU, one thread of numpy).

Objects drive straight at 3-15 m/s from random places 5-60 m ahead of an ego that drives at
10 m/s (poses given: world-frame tracking), detected every frame with 3 % depth noise and a
2D box; a tenth of the detections are missed at random and a few false ones added, so births,
deaths and both association stages happen. Each tracker (``kalman3d``, ``sort2d``,
``new_ids``) runs ``--frames`` frames (after ``--warmup``); reported: the median and the
90th percentile of ``update`` in wall ms and the median in CPU ms of its thread (what a loaded
machine's other processes do not add), over frames and ``--rounds`` streams, and the machine.
The target: at most 1 ms per frame at 50 objects for ``kalman3d``.

    python benchmarks/bench_tracker.py [--objects 10,50,100] [--frames 200] [--rounds 3]
        [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gac_jax.data.kitti import KittiObjects  # noqa: E402
from gac_jax.geometry import box2d_from_corners, box3d_corners  # noqa: E402
from gac_jax.tracking import METHODS, TrackerParams  # noqa: E402

P2 = np.array([[721.5, 0.0, 609.6, 44.9], [0.0, 721.5, 172.9, 0.2], [0.0, 0.0, 1.0, 0.003]])


def stream(objects: int, frames: int, seed: int):
    """Detections (KittiObjects) and poses of one synthetic stream."""
    rng = np.random.default_rng(seed)
    start = np.stack(
        [rng.uniform(-15, 15, objects), np.full(objects, 1.65), rng.uniform(5, 60, objects)], 1
    )
    speed = rng.uniform(3, 15, objects) * rng.choice([-1, 1], objects)
    for k in range(frames):
        t = k / 10
        pose = np.concatenate([np.eye(3), [[0.0], [0.0], [10.0 * t]]], axis=1)
        world = start + np.outer(speed * t, [0, 0, 1]) + [0, 0, 10.0 * t]
        cam = world - pose[:, 3]
        cam[:, 2] *= rng.normal(1.0, 0.03, objects)
        seen = (rng.random(objects) > 0.1) & (cam[:, 2] > 2)
        extra = rng.integers(0, 3)
        cam = np.concatenate(
            [
                cam[seen],
                np.stack(
                    [rng.uniform(-10, 10, extra), np.full(extra, 1.65), rng.uniform(5, 50, extra)],
                    1,
                ),
            ]
        )
        n = len(cam)
        ry = np.where(np.concatenate([speed[seen], np.ones(extra)]) > 0, -np.pi / 2, np.pi / 2)
        dims = np.tile([1.5, 1.7, 4.2], (n, 1))
        boxes = box2d_from_corners(box3d_corners(cam, dims, ry), P2)
        det = KittiObjects.from_arrays(
            type=np.array(["Car"] * n),
            location=cam,
            dimensions=dims,
            rotation_y=ry,
            bbox=np.nan_to_num(boxes),
            score=rng.uniform(0.5, 1.0, n),
        )
        yield det, pose, t


def time_method(method: str, objects: int, frames: int, warmup: int, rounds: int):
    """Wall and CPU (this thread's) ms of each ``update`` after the warm-up frames."""
    times, cpu = [], []
    for r in range(rounds):
        tracker = METHODS[method](TrackerParams())
        data = list(stream(objects, frames + warmup, seed=r))
        for k, (det, pose, t) in enumerate(data):
            t0, c0 = time.perf_counter(), time.thread_time()
            tracker.update(det, pose=pose, timestamp=t)
            if k >= warmup:
                times.append(1e3 * (time.perf_counter() - t0))
                cpu.append(1e3 * (time.thread_time() - c0))
    return times, cpu


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--objects", default="10,50,100")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument("--warmup", type=int, default=10)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--json", help="write the figures here too")
    args = p.parse_args(argv)
    machine = describe_machine("numpy", "scipy")
    print(one_line(machine))
    rows = []
    for n in [int(v) for v in args.objects.split(",")]:
        for method in METHODS:
            times, cpu = time_method(method, n, args.frames, args.warmup, args.rounds)
            row = {
                "method": method,
                "objects": n,
                "median_ms": statistics.median(times),
                "p90_ms": float(np.percentile(times, 90)),
                "median_cpu_ms": statistics.median(cpu),
                "frames": len(times),
            }
            rows.append(row)
            print(
                f"{method:9s} {n:4d} objects: median {row['median_ms']:.3f} ms, "
                f"p90 {row['p90_ms']:.3f} ms per frame, CPU median {row['median_cpu_ms']:.3f} ms "
                f"({len(times)} frames)",
                flush=True,
            )
    if args.json:
        Path(args.json).write_text(json.dumps({"machine": machine, "rows": rows}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
