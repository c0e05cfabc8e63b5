"""Times the KITTI tracking evaluator on a generated KITTI-tracking-sized set.

21 sequences of 380 frames (7,980 frames), about 30,000 ground-truth boxes (Car, Van,
Pedestrian, Person, Cyclist, DontCare) moving in 3D in front of a KITTI camera, boxes in
the image from their projection; results: the ground truth with 2D/3D noise, misses, id
switches and false positives, with scores. Written to a temporary folder, then read and
scored as ``evaluate.py --task track`` does (HOTA, CLEAR, IDF1 for Car and Pedestrian; then
with the 3D MOT block: sAMOTA/AMOTA/AMOTP at 3D IoU 0.25 and 0.5 by each rule, and the
velocity error).

    python benchmarks/bench_track_eval.py [--sequences 21] [--frames 380] [--repeats 3] [--keep DIR]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine_info import describe_machine, one_line  # noqa: E402  (benchmarks/ is on sys.path)

from gac_jax.evaluation.tracking.evaluator import (  # noqa: E402
    evaluate_tracking,
    format_tracking_table,
    load_tracking_folders,
)

FOCAL, CX, CY = 721.5, 609.6, 172.9
SIZES = {"Car": (1.5, 1.6, 3.9), "Van": (2.2, 1.9, 5.0), "Pedestrian": (1.75, 0.6, 0.8)}
SIZES |= {"Person": (1.3, 0.6, 0.8), "Cyclist": (1.7, 0.6, 1.8)}
TYPES = ("Car", "Car", "Car", "Car", "Van", "Pedestrian", "Pedestrian", "Person", "Cyclist")


def _line(frame, tid, typ, box, dims, loc, ry, score=None, occ=0):
    x1, y1, x2, y2 = box
    text = (
        f"{frame} {tid} {typ} 0 {occ} -10 "
        f"{x1:.2f} {y1:.2f} {x2:.2f} {y2:.2f} {dims[0]:.2f} {dims[1]:.2f} {dims[2]:.2f} "
        f"{loc[0]:.2f} {loc[1]:.2f} {loc[2]:.2f} {ry:.2f}"
    )
    return text + (f" {score:.3f}\n" if score is not None else "\n")


def _project(loc, dims):
    h, w, _ = dims
    z = loc[2]
    u = FOCAL * loc[0] / z + CX
    half = FOCAL * w / z
    top = FOCAL * (loc[1] - h) / z + CY
    bottom = FOCAL * loc[1] / z + CY
    return (u - half, top, u + half, bottom)


def generate(root: Path, n_seq: int, n_frames: int, seed: int = 0) -> int:
    """Writes ``label_02``, ``results`` and the seqmap; returns the number of ground-truth boxes."""
    rng = np.random.default_rng(seed)
    (root / "label_02").mkdir(parents=True)
    (root / "results").mkdir()
    total = 0
    for s in range(n_seq):
        gt, res = [], []
        next_id = 1000
        for obj in range(24):
            typ = TYPES[rng.integers(len(TYPES))]
            start = int(rng.integers(0, n_frames - 10))
            length = int(rng.integers(10, min(n_frames - start, 200) + 1))
            loc = np.array([rng.uniform(-12, 12), 1.65, rng.uniform(6, 50)])
            vel = np.array([rng.normal(0, 0.05), 0.0, rng.normal(0, 0.6)])
            dims = SIZES[typ]
            tid = next_id
            for f in range(start, start + length):
                loc = loc + vel
                if loc[2] < 4:
                    break
                box = _project(loc, dims)
                occ = int(rng.integers(0, 3))
                gt.append((f, _line(f, obj, typ, box, dims, loc, 0.1, occ=occ)))
                total += 1
                if rng.random() < 0.12:
                    continue
                if rng.random() < 0.01:
                    next_id += 1
                    tid = next_id
                noisy = loc + rng.normal(0, 0.02 * loc[2], 3) * (1, 0.1, 1)
                jitter = np.array(box) + rng.normal(0, 3, 4)
                rtype = {"Van": "Car", "Person": "Pedestrian"}.get(typ, typ)
                res.append((f, _line(f, tid, rtype, jitter, dims, noisy, 0.1, rng.random())))
            next_id += 1
        for f in range(n_frames):
            if rng.random() < 0.4:
                loc = np.array([rng.uniform(-12, 12), 1.65, rng.uniform(6, 50)])
                box = _project(loc, SIZES["Car"])
                res.append((f, _line(f, next_id, "Car", box, SIZES["Car"], loc, 0.0, 0.2)))
                next_id += 1
            if rng.random() < 0.3:
                x, y = rng.uniform(0, 1100), rng.uniform(120, 200)
                dc = f"{f} -1 DontCare -1 -1 -10 {x:.2f} {y:.2f} {x + 40:.2f} {y + 30:.2f}"
                gt.append((f, dc + " -1 -1 -1 -1000 -1000 -1000 -10\n"))
        for name, rows in (("label_02", gt), ("results", res)):
            rows.sort(key=lambda r: r[0])
            (root / name / f"{s:04d}.txt").write_text("".join(r[1] for r in rows))
    seqmap = "".join(f"{s:04d} empty 000000 {n_frames:06d}\n" for s in range(n_seq))
    (root / "evaluate_tracking.seqmap.training").write_text(seqmap)  # the sequences' lengths
    return total


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sequences", type=int, default=21)
    parser.add_argument("--frames", type=int, default=380)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--keep", metavar="DIR", help="write the set to DIR (new) and keep it")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(args.keep or tmp)
        n_gt = generate(root, args.sequences, args.frames)
        times = {"read": [], "2D (HOTA, CLEAR, IDF1)": []}
        times |= {f"with 3D MOT ({rule}) + velocity": [] for rule in ("ab3dmot", "trackeval")}
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            seqs = load_tracking_folders(root / "label_02", root / "results")
            t1 = time.perf_counter()
            evaluate_tracking(seqs, with_3d=False)
            t2 = time.perf_counter()
            result = evaluate_tracking(seqs, with_3d=True)  # the default rule, AB3DMOT's
            t3 = time.perf_counter()
            evaluate_tracking(seqs, with_3d=True, mot3d_rule="trackeval")
            t4 = time.perf_counter()
            times["read"].append(t1 - t0)
            times["2D (HOTA, CLEAR, IDF1)"].append(t2 - t1)
            times["with 3D MOT (ab3dmot) + velocity"].append(t3 - t2)
            times["with 3D MOT (trackeval) + velocity"].append(t4 - t3)
        n_res = sum(len(s.results) for s in seqs)
    print(format_tracking_table(result), end="")
    print(
        f"\n{args.sequences} sequences x {args.frames} frames, {n_gt} ground-truth lines, "
        f"{n_res} result lines; median of {args.repeats}:"
    )
    for name, t in times.items():
        print(f"  {name:<36} {statistics.median(t):7.2f} s")
    print("machine:", one_line(describe_machine("numpy", "scipy")))
    return 0


if __name__ == "__main__":
    sys.exit(main())
