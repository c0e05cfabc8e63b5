"""Benchmark of the synthetic KITTI generator: frames per second on this machine.

    python benchmarks/bench_synthetic.py [--num 1000] [--workers K] [--single 10]

Generates ``--num`` full frames (both views, dense + sparse depth, all PNG
encodes and links) into a temporary directory with a process pool, and reports
frames/s, total seconds and the median per-frame time; then renders and writes
``--single`` frames in this process alone and reports CPU and wall seconds per
frame (the per-core cost, less sensitive to other load on the machine).
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

from gac_jax.data.synthetic.writer import generate_dataset  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--num", type=int, default=1000, help="frames for the pooled run (0 = skip)")
    p.add_argument("--workers", type=int, default=None, help="processes (default: all cores)")
    p.add_argument("--single", type=int, default=10, help="frames for the one-process run")
    p.add_argument("--height", type=int, default=375)
    p.add_argument("--width", type=int, default=1242)
    p.add_argument("--out", default=None, help="directory to write into (default: a temp dir)")
    args = p.parse_args()
    report = {"machine": describe_machine("numpy", "cv2"), "image_size": [args.height, args.width]}
    tmp = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="bench_synthetic_"))
    try:
        if args.num > 0:
            start = time.perf_counter()
            result = generate_dataset(
                tmp / "pooled",
                args.num,
                0,
                height=args.height,
                width=args.width,
                workers=args.workers,
                progress=True,
            )
            total = time.perf_counter() - start
            report["pooled"] = {
                "frames": args.num,
                "workers": args.workers or os.cpu_count(),
                "total_s": round(total, 2),
                "frames_per_s": round(args.num / total, 3),
                "median_frame_s": round(statistics.median(result.frame_seconds), 4),
                "bytes_per_frame": sum(
                    f.stat().st_size
                    for f in (tmp / "pooled").rglob("*.png")
                    if "raw" not in f.parts
                )
                // args.num,
            }
        if args.single > 0:
            generate_dataset(tmp / "warmup", 1, 99, height=args.height, width=args.width, workers=1)
            cpu, wall = time.process_time(), time.perf_counter()
            result = generate_dataset(
                tmp / "single", args.single, 1, height=args.height, width=args.width, workers=1
            )
            report["single_process"] = {
                "frames": args.single,
                "cpu_s_per_frame": round((time.process_time() - cpu) / args.single, 4),
                "wall_s_per_frame": round((time.perf_counter() - wall) / args.single, 4),
                "median_frame_s": round(statistics.median(result.frame_seconds), 4),
            }
    finally:
        if not args.out:
            shutil.rmtree(tmp, ignore_errors=True)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
