"""The inference API's latency per image: ``Detector3D.predict`` and its three stages (CPU).

A trained detector workdir (``--workdir``; read only: exports go to a temporary folder) is
loaded through :class:`gac_jax.api.Detector3D` once per runtime (``jax``, ``onnxruntime``,
``openvino``; f32, batch 1) and run on real KITTI frames (``../shared/data/kitti_samples``,
else the vendored ones), the runtimes interleaved (every round runs each runtime on every
frame, so a shared machine's load hits them alike). Reported per runtime: the first call
(jax: includes the jit compile; the others: load + export / warm-up in ``load_s``) and the
medians over rounds x frames of ``prepare`` (checks + test transform), ``infer`` (network +
jitted decoding / top-k), ``finish`` (NMS, hill-climbing, original pixels) and of a whole
``predict`` call, in wall ms; the detections per frame; and the machine with its load.

    python benchmarks/bench_api.py --workdir W [--runtimes jax,onnxruntime,openvino]
        [--rounds 5] [--frames 4] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
from gac_jax.cpu_backend import apply_default_xla_flags  # noqa: E402

apply_default_xla_flags()

KITTI_ROOTS = (
    REPO.parent / "shared" / "data" / "kitti_samples" / "object",
    REPO / "tests" / "data" / "kitti" / "object",
)


def kitti_frames(count: int) -> list[tuple[str, object, object]]:
    """(frame id, RGB image, P2) of the first ``count`` labelled KITTI sample frames."""
    from gac_jax.data.files import read_image
    from gac_jax.data.kitti import KittiObjectLayout, read_calib

    root = next(r for r in KITTI_ROOTS if (r / "training" / "calib").is_dir())
    layout = KittiObjectLayout(root)
    ids = sorted(p.stem for p in (root / "training" / "image_2").glob("*.png"))[:count]
    return [(f, read_image(layout.image(f)), read_calib(layout.calib(f)).P2) for f in ids]


def timed(fn, *args):
    t0 = time.perf_counter()
    out = fn(*args)
    return out, (time.perf_counter() - t0) * 1e3


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workdir", required=True, help="trained detector workdir (read only)")
    parser.add_argument("--runtimes", default="jax,onnxruntime,openvino")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--frames", type=int, default=4)
    parser.add_argument("--json", help="write the results here")
    args = parser.parse_args(argv)

    from gac_jax.api import Detector3D

    frames = kitti_frames(args.frames)
    runtimes = args.runtimes.split(",")
    detectors, first = {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        for runtime in runtimes:
            t0 = time.perf_counter()
            det = Detector3D.from_workdir(args.workdir, runtime=runtime, export_dir=tmp)
            load_s = time.perf_counter() - t0
            _, first_ms = timed(det.predict, frames[0][1], frames[0][2])
            detectors[runtime] = det
            first[runtime] = {"load_s": round(load_s, 2), "first_predict_ms": round(first_ms, 1)}
            print(f"{det!r}: loaded in {load_s:.1f} s, first predict {first_ms:.0f} ms", flush=True)
        samples = {r: {"prepare": [], "infer": [], "finish": [], "predict": []} for r in runtimes}
        counts = {r: [] for r in runtimes}
        for _ in range(args.rounds):
            for runtime in runtimes:
                det, s = detectors[runtime], samples[runtime]
                for _, image, P2 in frames:
                    prepared, ms = timed(det.prepare, image, P2)
                    s["prepare"].append(ms)
                    raw, ms = timed(det.infer, [prepared])
                    s["infer"].append(ms)
                    _, ms = timed(det.finish, raw, [prepared])
                    s["finish"].append(ms)
                    dets, ms = timed(det.predict, image, P2)
                    s["predict"].append(ms)
                    counts[runtime].append(len(dets))
    machine = describe_machine("jax", "numpy")
    print(
        f"\n{det.weights}, input {det.input_size[0]}x{det.input_size[1]}, batch 1, "
        f"{args.rounds} rounds x {len(frames)} KITTI frames; median wall ms per image"
    )
    print(
        f"{'runtime':<12} {'prepare':>8} {'infer':>8} {'finish':>8} {'predict':>8} "
        f"{'img/s':>6} {'dets':>5}"
    )
    results = {}
    for runtime in runtimes:
        med = {k: statistics.median(v) for k, v in samples[runtime].items()}
        results[runtime] = {**{f"{k}_ms": round(v, 2) for k, v in med.items()}, **first[runtime]}
        results[runtime]["detections_per_frame"] = statistics.mean(counts[runtime])
        print(
            f"{runtime:<12} {med['prepare']:8.1f} {med['infer']:8.1f} {med['finish']:8.1f} "
            f"{med['predict']:8.1f} {1e3 / med['predict']:6.2f} "
            f"{statistics.mean(counts[runtime]):5.1f}"
        )
    print(f"machine: {one_line(machine)}")
    out = {"results": results, "machine": machine, "weights": det.weights,
           "rounds": args.rounds, "frames": [f for f, _, _ in frames]}  # fmt: skip
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
