"""Times the KITTI detection evaluator on a generated KITTI-val-sized set (3,769 frames).

Ground truth: random KITTI-like scenes (Car, Van, Pedestrian, Cyclist, DontCare) with
3D boxes on the ground in front of a KITTI camera, 2D boxes from their projection
clipped to a 375x1242 image, truncation from the clipped fraction, random occlusion.
Detections: perturbed true positives (location noise growing with depth, size, yaw
and 2D jitter) with scores, misses, class confusions and false positives,
about 5-20 per frame. Everything is generated in memory with a fixed seed.

    python benchmarks/bench_kitti_eval.py [--frames 3769] [--repeats 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from machine_info import describe_machine, one_line  # noqa: E402  (benchmarks/ is on sys.path)

from gac_jax import geometry  # noqa: E402
from gac_jax.data.kitti import KittiObjects  # noqa: E402
from gac_jax.evaluation.ap_table import format_table  # noqa: E402
from gac_jax.evaluation.kitti_object import evaluate_detections  # noqa: E402

P2 = np.array(
    [
        [721.5377, 0.0, 609.5593, 44.85728],
        [0.0, 721.5377, 172.854, 0.2163791],
        [0.0, 0.0, 1.0, 0.002745884],
    ]
)
IMAGE_SIZE = (375, 1242)
# type, probability, mean (h, w, l), relative size spread
CLASS_TABLE = [
    ("Car", 0.58, (1.53, 1.63, 3.88), 0.08),
    ("Van", 0.06, (2.21, 1.90, 5.08), 0.10),
    ("Pedestrian", 0.16, (1.76, 0.66, 0.84), 0.10),
    ("Cyclist", 0.06, (1.74, 0.60, 1.76), 0.08),
    ("DontCare", 0.14, None, 0.0),
]


def _objects(rng, types, loc, dims, ry, score=None) -> KittiObjects:
    """KittiObjects with 2D boxes, truncation and alpha derived from the 3D boxes."""
    n = len(types)
    corners = geometry.box3d_corners(loc, dims, ry)
    full = geometry.box2d_from_corners(corners, P2)
    box = geometry.box2d_from_corners(corners, P2, image_size=IMAGE_SIZE)
    area_full = np.maximum((full[:, 2] - full[:, 0]) * (full[:, 3] - full[:, 1]), 1e-6)
    area_in = np.maximum(box[:, 2] - box[:, 0], 0) * np.maximum(box[:, 3] - box[:, 1], 0)
    trunc = np.clip(1.0 - area_in / area_full, 0.0, 1.0)
    occ = rng.choice(4, size=n, p=[0.55, 0.25, 0.15, 0.05])
    alpha = geometry.alpha_from_rotation_y(ry, loc)
    return KittiObjects.from_arrays(
        type=types,
        truncated=np.round(trunc, 2),
        occluded=occ,
        alpha=alpha,
        bbox=box,
        dimensions=dims,
        location=loc,
        rotation_y=ry,
        score=np.full(n, np.nan) if score is None else score,
    )


def _random_boxes(rng, n, kinds):
    dims = np.zeros((n, 3))
    types = np.empty(n, dtype="<U16")
    for i, k in enumerate(kinds):
        name, _, mean, spread = CLASS_TABLE[k]
        types[i] = name
        dims[i] = np.asarray(mean) * (1.0 + spread * rng.standard_normal(3))
    z = rng.uniform(4.0, 65.0, n)
    x = rng.uniform(-0.6, 0.6, n) * z + rng.normal(0, 2, n)
    y = 1.65 + rng.normal(0, 0.08, n)
    ry = rng.uniform(-np.pi, np.pi, n)
    return types, np.stack([x, y, z], 1), dims, ry


def generate_frame(rng) -> tuple[KittiObjects, KittiObjects]:
    """One frame: (ground truth with DontCare, detections with scores)."""
    probs = np.array([c[1] for c in CLASS_TABLE])
    n = int(rng.integers(1, 16))
    kinds = rng.choice(len(CLASS_TABLE), size=n, p=probs / probs.sum())
    real = kinds != len(CLASS_TABLE) - 1
    types, loc, dims, ry = _random_boxes(rng, int(real.sum()), kinds[real])
    keep = loc[:, 2] > 0
    gt = _objects(rng, types[keep], loc[keep], dims[keep], ry[keep])
    visible = (gt.bbox[:, 2] - gt.bbox[:, 0] > 1) & (gt.bbox[:, 3] - gt.bbox[:, 1] > 1)
    gt = gt.select(visible)
    n_dc = int((~real).sum())
    if n_dc:
        x1 = rng.uniform(0, IMAGE_SIZE[1] - 60, n_dc)
        y1 = rng.uniform(140, 220, n_dc)
        dc = KittiObjects.from_arrays(
            type=["DontCare"] * n_dc,
            truncated=np.full(n_dc, -1.0),
            occluded=np.full(n_dc, -1),
            alpha=np.full(n_dc, -10.0),
            bbox=np.stack(
                [x1, y1, x1 + rng.uniform(10, 60, n_dc), y1 + rng.uniform(8, 30, n_dc)], 1
            ),
            dimensions=np.full((n_dc, 3), -1.0),
            location=np.full((n_dc, 3), -1000.0),
            rotation_y=np.full(n_dc, -10.0),
        )
        gt = KittiObjects.concatenate([gt, dc])

    # Detections: perturbed true positives (80 %), some class confusion, plus false positives.
    obj = gt.select(gt.type != "DontCare")
    hit = rng.random(len(obj)) < 0.8
    tp = obj.select(hit)
    m = len(tp)
    z = tp.location[:, 2]
    loc = tp.location + rng.standard_normal((m, 3)) * np.stack(
        [0.004 * z + 0.03, np.full(m, 0.04), 0.015 * z + 0.05], 1
    )
    dims = tp.dimensions * (1.0 + 0.06 * rng.standard_normal((m, 3)))
    ry = tp.rotation_y + rng.normal(0, 0.15, m) + np.where(rng.random(m) < 0.1, np.pi, 0.0)
    tp_types = tp.type.copy()
    tp_types[tp_types == "Van"] = np.where(
        rng.random(int((tp_types == "Van").sum())) < 0.5, "Car", "Van"
    )
    confuse = rng.random(m) < 0.05
    tp_types[confuse] = rng.choice(["Car", "Pedestrian", "Cyclist"], size=int(confuse.sum()))
    scores_tp = np.clip(rng.beta(5, 2, m), 1e-3, 1.0)
    n_fp = int(rng.integers(2, 10))
    fkinds = rng.choice([0, 2, 3], size=n_fp, p=[0.6, 0.3, 0.1])
    ftypes, floc, fdims, fry = _random_boxes(rng, n_fp, fkinds)
    scores_fp = np.clip(rng.beta(2, 5, n_fp), 1e-3, 1.0)
    types = np.concatenate([tp_types, ftypes])
    dt = _objects(
        rng,
        types,
        np.concatenate([loc, floc]),
        np.abs(np.concatenate([dims, fdims])),
        np.concatenate([ry, fry]),
        score=np.round(np.concatenate([scores_tp, scores_fp]), 4),
    )
    # The 2D boxes of true positives are regressed separately: GT box + jitter of ~4 % of its size.
    size = np.abs(tp.bbox[:, 2:] - tp.bbox[:, :2])
    tp_box = tp.bbox + rng.standard_normal((m, 4)) * 0.04 * np.concatenate([size, size], 1)
    dt = dt.replace(bbox=np.concatenate([tp_box, dt.bbox[m:]]))
    ok = (
        (dt.location[:, 2] > 0.5)
        & (dt.bbox[:, 2] > dt.bbox[:, 0])
        & (dt.bbox[:, 3] > dt.bbox[:, 1])
    )
    dt = dt.select(ok & (dt.type != "Van"))
    return gt, dt


def generate_dataset(num_frames: int = 3769, seed: int = 0):
    rng = np.random.default_rng(seed)
    gts, dts = [], []
    for _ in range(num_frames):
        g, d = generate_frame(rng)
        gts.append(g)
        dts.append(d)
    return gts, dts


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3769)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--table", action="store_true", help="print the AP table of the last run")
    args = parser.parse_args(argv)

    t0 = time.perf_counter()
    gts, dts = generate_dataset(args.frames, args.seed)
    t_gen = time.perf_counter() - t0
    n_gt = sum(len(g) for g in gts)
    n_dt = sum(len(d) for d in dts)
    print(f"machine: {one_line(describe_machine('numpy'))}")
    print(
        f"data: {args.frames} frames, {n_gt} ground-truth objects, {n_dt} detections "
        f"({n_dt / args.frames:.1f}/frame), generated in {t_gen:.1f} s"
    )
    times = []
    cpu_times = []
    result = None
    for _ in range(args.repeats):
        c0, w0 = time.process_time(), time.perf_counter()
        result = evaluate_detections(gts, dts)
        times.append(time.perf_counter() - w0)
        cpu_times.append(time.process_time() - c0)
    print(
        f"evaluate_detections (3 classes x 3 difficulties x bbox/bev/3d/aos x 2 IoU settings, "
        f"R11+R40): median {statistics.median(times):.2f} s wall, "
        f"{statistics.median(cpu_times):.2f} s CPU; runs: "
        + ", ".join(f"{t:.2f}" for t in times)
        + f"; total {sum(times):.2f} s"
    )
    if args.table:
        print(format_table(result))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
