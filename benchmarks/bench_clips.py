"""Benchmark of driving-clip rendering: frames per second on this machine.

    python benchmarks/bench_clips.py [--sequences 1] [--frames 100] [--workers K] [--single 10]
        [--scenarios default|all|none]

Generates ``--sequences`` clips of ``--frames`` frames (left view, labels with track ids,
planes, poses, PNG encodes) into a temporary directory with a process pool and reports
frames/s, total seconds and the median per-frame time; then one short clip of ``--single``
frames in this process alone (CPU and wall seconds per frame: the per-core cost, less
sensitive to other load on the machine); and the median time to sample a sequence's world
(road, roadside, road users and their motion over the clip) of ``--frames`` frames.
``--scenarios``: the default mix, every scenario in every sequence, or none (straight
roads, constant speeds).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine_info import describe_machine  # noqa: E402  (benchmarks/ is on sys.path)

from gac_jax.data.synthetic import drive, traffic  # noqa: E402
from gac_jax.data.synthetic.clips import generate_clips  # noqa: E402

MIXES = {
    "default": dict(traffic.DEFAULT_MIX),
    "all": {name: 1.0 for name in traffic.SCENARIOS},
    "none": {},
}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sequences", type=int, default=1, help="clips of the pooled run (0 = skip)")
    p.add_argument("--frames", type=int, default=100, help="frames per clip")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--single", type=int, default=10, help="frames for the one-process run")
    p.add_argument("--rigs", default="kitti", choices=("kitti", "multi"))
    p.add_argument("--height", type=int, default=375)
    p.add_argument("--width", type=int, default=1242)
    p.add_argument("--scenarios", default="default", choices=tuple(MIXES))
    p.add_argument("--worlds", type=int, default=5, help="sequences' worlds sampled (0 = skip)")
    args = p.parse_args()
    mix = MIXES[args.scenarios]
    size = dict(height=args.height, width=args.width, rigs=args.rigs, scenarios=mix)
    report = {"machine": describe_machine("numpy", "cv2"), "image_size": [args.height, args.width]}
    report["rigs"] = args.rigs
    report["scenarios"] = args.scenarios
    tmp = Path(tempfile.mkdtemp(prefix="bench_clips_"))
    try:
        if args.sequences > 0:
            start = time.perf_counter()
            result = generate_clips(
                tmp / "pooled", args.sequences, args.frames, 0, workers=args.workers, **size,
                progress=True,
            )  # fmt: skip
            total = time.perf_counter() - start
            n = args.sequences * args.frames
            report["pooled"] = {
                "sequences": args.sequences,
                "frames_per_sequence": args.frames,
                "workers": args.workers or os.cpu_count(),
                "total_s": round(total, 2),
                "frames_per_s": round(n / total, 3),
                "median_frame_s": round(statistics.median(result.frame_seconds), 4),
                "bytes_per_frame": sum(f.stat().st_size for f in (tmp / "pooled").rglob("*.png"))
                // n,
            }
        if args.single > 0:
            generate_clips(tmp / "warmup", 1, 1, 99, workers=1, **size)
            cpu, wall = time.process_time(), time.perf_counter()
            result = generate_clips(tmp / "single", 1, args.single, 1, workers=1, **size)
            report["single_process"] = {
                "frames": args.single,
                "cpu_s_per_frame": round((time.process_time() - cpu) / args.single, 4),
                "wall_s_per_frame": round((time.perf_counter() - wall) / args.single, 4),
                "median_frame_s": round(statistics.median(result.frame_seconds), 4),
            }
        if args.worlds > 0:
            seconds = []
            for sequence in range(args.worlds):
                start = time.perf_counter()
                drive.make_drive(
                    0, sequence, args.frames, (args.height, args.width), None, args.rigs,
                    tuple(mix.items()),
                )  # fmt: skip
                seconds.append(time.perf_counter() - start)
            report["world_sampling"] = {
                "sequences": args.worlds,
                "frames_per_sequence": args.frames,
                "median_s": round(statistics.median(seconds), 3),
            }
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
