"""A video file's decoding cost per frame with one FFmpeg thread (a stream's budget) and with
FFmpeg's own thread count (every core).

The stream's source (``gac_jax.streams.sources.VideoSource``) decodes an MPEG-4 video of the
KITTI sample frames (1242x375, as ``bench_stream.py`` makes it) to RGB through PyAV (FFmpeg's
decoder and colour conversion), frame after frame; each setting is timed in alternation over
``--rounds`` passes: the process CPU time per frame (the decoder's threads included) and the
wall time per frame. Reported: medians over rounds, and the machine. A stream's read stage
runs beside four other stages on the same cores, so what counts there is the CPU time: with one
thread the decoding costs the CPU it needs, with several the threads' hand-offs add to it.

    python benchmarks/bench_video_decode.py [--frames 120] [--rounds 5] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from bench_stream import make_video  # benchmarks/ is on sys.path
from machine_info import describe_machine, one_line

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gac_jax.streams import sources  # noqa: E402
from gac_jax.streams.thread_budget import apply_host_threads, plan_thread_budget  # noqa: E402

SETTINGS = {"1 thread (stream budget)": 1, "FFmpeg's default": None}


def one_pass(video: Path, calib: Path, threads: int | None) -> tuple[float, float, int, int]:
    """(CPU ms per frame, wall ms per frame, frames, decoder threads reported)."""
    source = sources.VideoSource(
        video, sources.load_projection(calib), str(calib), decode_threads=threads
    )
    try:
        reported = source.decode_threads
        c0, t0, n = time.process_time(), time.perf_counter(), 0
        while source.read() is not None:
            n += 1
        cpu, wall = time.process_time() - c0, time.perf_counter() - t0
    finally:
        source.close()
    return 1e3 * cpu / n, 1e3 * wall / n, n, reported


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--frames", type=int, default=120)
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--json", type=Path)
    args = p.parse_args()
    sources.quiet_video_backend()
    apply_host_threads(plan_thread_budget())  # OpenCV and BLAS: one thread, as in a stream
    info = describe_machine("cv2")
    print(one_line(info))
    rows = {name: [] for name in SETTINGS}
    with tempfile.TemporaryDirectory(prefix="bench_decode_") as tmp:
        video, calib = make_video(Path(tmp) / "input.mp4", args.frames)
        for threads in SETTINGS.values():  # warm-up (file cache, codec set-up)
            one_pass(video, calib, threads)
        for _ in range(args.rounds):
            for name, threads in SETTINGS.items():
                rows[name].append(one_pass(video, calib, threads))
    print(f"{args.frames}-frame 1242x375 MPEG-4 video, decoded to RGB; medians of {args.rounds}")
    result = {}
    for name, runs in rows.items():
        cpu = statistics.median(r[0] for r in runs)
        wall = statistics.median(r[1] for r in runs)
        result[name] = {"cpu_ms": cpu, "wall_ms": wall, "decoder_threads": runs[0][3]}
        print(
            f"  {name:26s} decoder threads {runs[0][3]}: CPU {cpu:5.2f} ms per frame, "
            f"wall {wall:5.2f} ms per frame"
        )
    if args.json:
        args.json.write_text(json.dumps({"machine": info, "settings": result}))


if __name__ == "__main__":
    main()
