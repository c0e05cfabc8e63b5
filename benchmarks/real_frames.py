"""How a detector (and a depth network) trained on generated data does on real KITTI frames.

Scores a run folder on the real, labelled KITTI frames of ``../shared/data/kitti_samples``
(``object/``, split ``labeled``: 13 frames) and, for the same weights, on the generated val
split it was trained beside, so that tuning to the 13 real frames shows:

* Car AP|R40 (easy / moderate / hard) for 2D @0.7, BEV @0.7 / @0.5 and 3D @0.7 / @0.5, as
  ``evaluate.py`` computes them;
* detections and false positives per frame at the run's evaluation score threshold
  (``eval.score_threshold``, every box AP counts). A false positive is a Car detection that
  overlaps no labelled Car (2D IoU >= 0.5, each labelled car taken by one detection, highest
  score first) and is not excused the way the KITTI benchmark excuses it: overlapping a Van
  (IoU >= 0.5) or lying at least half inside a DontCare region;
* the real labelled cars at least 25 px tall that some detection finds at IoU 0.5 / 0.7;
* Car 2D AP|R40 at IoU 0.5 (KITTI scores cars at 0.7: the difference is box looseness),
  and false positives per frame and cars found at score thresholds 0.5 to 0.9;
* how the boxes of the cars found are off: over the labelled cars at least 25 px tall that a
  detection at the evaluation threshold overlaps at IoU >= 0.5 (the best one), the medians of
  detected / labelled 2D box width and height and of detected / labelled depth ``z`` (a
  detector that sees real cars as smaller or farther than its generated ones shows it here,
  and such a scale bias alone keeps boxes under KITTI's IoU 0.7);
* a picture grid of the 13 frames (``OUT/real/pictures/grid.png``);
* with the generated val split scored: the run's operating point chosen there
  (``gac_jax/evaluation/operating_point.py``: the score threshold of best F-beta, beta from
  the run's ``eval.operating_point_beta``, on a grid from ``eval.score_threshold`` to 0.95; the
  one the final evaluation of training records and a default run deploys), the real frames'
  false positives and cars found at that threshold, and their picture grid there
  (``OUT/real/pictures_operating_point/grid.png``). Nothing real chooses it.

``--steps S ...`` also scores those earlier checkpoints of the run on the real frames and
prints each figure's mean and range over the checkpoints: 13 frames (32 cars) and one
training run are noisy, and the spread between checkpoints a few hundred steps apart shows
how much a single figure can be trusted.

``--depth-workdir D`` also scores a depth run on the real KITTI-depth frame (``depth/``,
split ``train``) beside the ground-plane prior alone. ``--clip`` runs the detector with
``--track`` over the real raw drive of ``raw_clip/`` (KITTI raw layout, the day's
calibration found in its date folder) and reports the tracks it made.

    python benchmarks/real_frames.py --workdir W [--depth-workdir D] [--out DIR] [--clip]
        [--samples ../shared/data/kitti_samples] [--no-generated] [--json OUT] [--steps S ...]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402

from gac_jax.data.kitti import parse_label, read_label, read_split  # noqa: E402
from gac_jax.detection.nms import box_iou_matrix  # noqa: E402
from gac_jax.evaluation.operating_point import (  # noqa: E402
    MIN_HEIGHT_PX,
    frame_counts,
    tall_objects,
    threshold_sweep,
)

SWEEP = (0.5, 0.6, 0.7, 0.8, 0.9)  # score thresholds of the false-positive sweep


def box_scale(gts: list, dts: list, threshold: float) -> dict:
    """Medians of detected / labelled 2D width, height and depth of the cars found.

    Over the labelled Cars at least MIN_HEIGHT_PX tall of all frames, each with the
    detection (Car, score >= ``threshold``) that overlaps it most, if at IoU >= 0.5.
    """
    ratios = []
    for gt, dt in zip(gts, dts, strict=True):
        keep = (dt.type == "Car") & (dt.score >= threshold)
        cars = np.flatnonzero(gt.type == "Car")
        cars = cars[(gt.bbox[cars, 3] - gt.bbox[cars, 1]) >= MIN_HEIGHT_PX]
        if not keep.any() or not len(cars):
            continue
        boxes, locs = dt.bbox[keep], dt.location[keep]
        iou = box_iou_matrix(gt.bbox[cars], boxes)
        for row, j in enumerate(cars):
            i = int(np.argmax(iou[row]))
            if iou[row, i] < 0.5:
                continue
            g, d = gt.bbox[j], boxes[i]
            ratios.append(
                (
                    (d[2] - d[0]) / max(g[2] - g[0], 1e-6),
                    (d[3] - d[1]) / max(g[3] - g[1], 1e-6),
                    locs[i, 2] / max(gt.location[j, 2], 1e-6),
                )
            )
    med = np.median(np.array(ratios), axis=0) if ratios else np.full(3, np.nan)
    return {"cars": len(ratios), "width": med[0], "height": med[1], "depth": med[2]}


def car_row(metrics: dict) -> dict:
    """Car AP|R40 entries (easy, moderate, hard) of an ``evaluate.py`` result dict."""
    car = metrics["ap40"]["Car"]
    return {
        "2d@0.7": car["0.70"]["bbox"],
        "bev@0.7": car["0.70"]["bev"],
        "3d@0.7": car["0.70"]["3d"],
        "bev@0.5": car["0.50"]["bev"],
        "3d@0.5": car["0.50"]["3d"],
    }


def loose_2d_ap40(gts: list, dts: list) -> list[float]:
    """Car 2D AP|R40 (easy, moderate, hard) at IoU 0.5, the devkit's rules otherwise.

    KITTI scores Car boxes at 0.7; at 0.5 the same detections show how much of the 2D
    figure is box looseness rather than missing or false detections.
    """
    from gac_jax.evaluation.kitti_object import DetectionEvalSet, average_precision

    evalset = DetectionEvalSet(gts, dts)
    return [
        average_precision(evalset.precision_curves("Car", d, "bbox", 0.5)[0], 40) for d in range(3)
    ]


def score_real(workdir: Path, samples: Path, out: Path, step: int | None = None) -> dict:
    from gac_jax.cli.evaluate_detector import evaluate_detector_workdir
    from gac_jax.trained.run_config import load_run_config

    root = samples / "object"
    summary = evaluate_detector_workdir(
        workdir, data_root=root, split="labeled", step=step, save_images=13, out_dir=out / "real"
    )
    threshold = float(load_run_config(workdir, None, None, root).eval.score_threshold)
    ids = read_split(root / "ImageSets" / "labeled.txt")
    result_dir = Path(summary["result_dir"])
    totals = np.zeros(4, np.int64)
    gts, dts = [], []
    for fid in ids:
        gt = read_label(root / "training" / "label_2" / f"{fid}.txt")
        path = result_dir / f"{fid}.txt"
        dt = read_label(path, with_score=True) if path.exists() else None
        gts.append(gt)
        dts.append(dt if dt is not None else parse_label("", with_score=True))
        if dt is not None and len(dt):
            totals += frame_counts(gt, dt, threshold)
    n = len(ids)
    sweep = threshold_sweep(gts, dts, SWEEP)
    return {
        "frames": n,
        "score_threshold": threshold,
        "ap40": {**car_row(summary["metrics"]), "2d@0.5": loose_2d_ap40(gts, dts)},
        "detections_per_frame": totals[0] / n,
        "false_positives_per_frame": totals[1] / n,
        "cars_25px": sum(tall_objects(g) for g in gts),
        "box_scale": box_scale(gts, dts, threshold),
        "found_iou50": int(totals[2]),
        "found_iou70": int(totals[3]),
        "sweep": {
            f"{t:g}": {"false_positives_per_frame": v["false_positives"], "found_iou50": v["found"]}
            for t, v in sweep.items()
        },
        "weights": summary["weights"],
        "pictures": str(out / "real" / "pictures" / "grid.png"),
        "_frames": (gts, dts),  # for the operating point; not written to JSON
    }


def score_generated(workdir: Path, out: Path) -> dict:
    from gac_jax.cli.evaluate_detector import evaluate_detector_workdir

    summary = evaluate_detector_workdir(workdir, out_dir=out / "generated_val")
    record = summary["operating_point"]  # gac_jax/evaluation/operating_point.py
    return {
        "ap40": car_row(summary["metrics"]),
        "frames": summary["num_frames"],
        "sweep": record["sweep"],
        "operating_point": record["threshold"],
        "operating_point_beta": record["beta"],
    }


def operating_point_pictures(samples: Path, dts: list, threshold: float, out: Path) -> Path:
    """The picture grid of the real frames at the operating point (what predict and the streams
    of a default run show), labels drawn as in the evaluation's grid; returns its path."""
    from gac_jax.data.sources import open_object_source
    from gac_jax.drawing.detection_pictures import save_pictures

    source = open_object_source(samples / "object", "labeled", use_right_image=False)
    ids = read_split(samples / "object" / "ImageSets" / "labeled.txt")
    kept = {fid: dt.select(dt.score >= threshold) for fid, dt in zip(ids, dts, strict=True)}
    folder = out / "real" / "pictures_operating_point"
    save_pictures(source, kept, folder, ("Car",), frame_ids=ids)
    return folder / "grid.png"


def score_depth(depth_workdir: Path, samples: Path, out: Path) -> dict:
    from gac_jax.cli.evaluate_depth import evaluate_baseline, evaluate_workdir

    data = str(samples / "depth")
    net = evaluate_workdir(depth_workdir, data=data, split="train", out=out / "depth_net")
    prior = evaluate_baseline("ground-plane", data=data, split="train", out=out / "depth_prior")
    keys = ("silog", "abs_rel", "sq_rel", "irmse", "rmse", "delta1")
    return {
        "network": {k: net["metrics"][k] for k in keys},
        "ground_plane_prior": {k: prior["metrics"][k] for k in keys},
        "step": net.get("step"),
    }


def run_clip(workdir: Path, samples: Path, out: Path) -> dict:
    drive = samples / "raw_clip" / "2011_09_26" / "2011_09_26_drive_unknown_sync"
    target = out / "raw_clip"
    cmd = [
        sys.executable, "-m", "gac_jax.cli.predict", "--workdir", str(workdir),
        "--sequence", str(drive), "--track", "--out", str(target), "--overwrite",
    ]  # fmt: skip
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:]
        return {"exit": proc.returncode, "error": tail[0] if tail else "", "wall_s": wall}
    ids = set()
    frames = 0
    for f in sorted((target / "tracking").glob("*.txt")):
        for line in f.read_text().splitlines():
            parts = line.split()
            if len(parts) > 2:
                ids.add(int(parts[1]))
                frames = max(frames, int(parts[0]) + 1)
    return {
        "exit": 0,
        "tracks": len(ids),
        "max_id": max(ids) if ids else None,
        "frames_with_objects": frames,
        "video": str(target / "annotated.mp4"),
        "wall_s": wall,
    }


def fmt(values) -> str:
    return " / ".join(f"{v:.2f}" for v in values)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--workdir", required=True, type=Path, help="a trained detector's run folder")
    p.add_argument("--depth-workdir", type=Path, help="also score this depth run")
    p.add_argument("--samples", type=Path, default=REPO.parent / "shared/data/kitti_samples")
    p.add_argument("--out", type=Path, help="output folder (default: W/real_frames)")
    p.add_argument("--no-generated", action="store_true", help="skip the generated val split")
    p.add_argument("--clip", action="store_true", help="also run --track over the raw drive")
    p.add_argument("--json", type=Path, help="write the results as JSON")
    p.add_argument(
        "--steps",
        type=int,
        nargs="+",
        metavar="STEP",
        help="also score these earlier checkpoints on the real frames and print the spread "
        "(13 frames and one training run are noisy: checkpoints a few hundred steps apart "
        "show how much)",
    )
    args = p.parse_args()
    if not (args.samples / "object" / "ImageSets" / "labeled.txt").is_file():
        sys.exit(f"error: {args.samples}: not the kitti_samples folder (object/ImageSets missing)")
    out = args.out or args.workdir / "real_frames"
    info = describe_machine("jax", "numpy")
    print("machine:", one_line(info), flush=True)
    result: dict = {"machine": info, "workdir": str(args.workdir)}
    result["real"] = score_real(args.workdir, args.samples, out)
    if not args.no_generated:
        result["generated_val"] = score_generated(args.workdir, out)
    if args.depth_workdir:
        result["depth"] = score_depth(args.depth_workdir, args.samples, out)
    if args.clip:
        result["clip"] = run_clip(args.workdir, args.samples, out)
    gts, dts = result["real"].pop("_frames")
    if "generated_val" in result and result["generated_val"]["operating_point"] is not None:
        t = result["generated_val"]["operating_point"]
        result["real"]["at_operating_point"] = {
            "threshold": t,
            **threshold_sweep(gts, dts, [t])[t],
            "pictures": str(operating_point_pictures(args.samples, dts, t, out)),
        }

    r = result["real"]
    print(f"\nmachine: {one_line(describe_machine())}")
    print(f"weights: {r['weights']}; evaluation score threshold {r['score_threshold']}")
    print("Car AP|R40 easy / moderate / hard:")
    sets = [("real (13 frames)", r["ap40"])]
    if "generated_val" in result:
        g = result["generated_val"]
        sets.append((f"generated val ({g['frames']} frames)", g["ap40"]))
    for name, row in sets:
        print(f"  {name}: " + "; ".join(f"{k} {fmt(v)}" for k, v in row.items()))
    print(
        f"real frames: {r['detections_per_frame']:.2f} detections and "
        f"{r['false_positives_per_frame']:.2f} false positives per frame; of the "
        f"{r['cars_25px']} cars >= 25 px tall, {r['found_iou50']} found at IoU 0.5, "
        f"{r['found_iou70']} at IoU 0.7; pictures: {r['pictures']}"
    )
    b = r["box_scale"]
    print(
        f"  boxes of the {b['cars']} cars found at IoU 0.5, detected / labelled (medians): "
        f"2D width {b['width']:.3f}, height {b['height']:.3f}, depth {b['depth']:.3f}"
    )
    print(
        "  at other score thresholds (false positives per frame, cars found at IoU 0.5): "
        + "; ".join(
            f"{t} {v['false_positives_per_frame']:.2f}, {v['found_iou50']}"
            for t, v in r["sweep"].items()
        )
    )
    if "at_operating_point" in r:
        o = r["at_operating_point"]
        g = result["generated_val"]["sweep"][f"{o['threshold']:.2f}"]
        beta = result["generated_val"]["operating_point_beta"]
        print(
            f"  at the operating point chosen on generated val (score {o['threshold']:g}, best "
            f"F{beta:g} there: precision {g['precision']:.2f}, recall {g['recall']:.2f}, "
            f"{g['false_positives']:.2f} false positives per frame): real frames "
            f"{o['false_positives']:.2f} false positives per frame, {o['found']} cars found at "
            f"IoU 0.5, precision {o['precision']:.2f}, recall {o['recall']:.2f}; pictures: "
            f"{o['pictures']}"
        )
    if "depth" in result:
        d = result["depth"]
        for name in ("network", "ground_plane_prior"):
            m = d[name]
            print(
                f"real depth frame, {name}: SILog {m['silog']:.2f}, "
                f"absRel {m['abs_rel']:.2f} %, sqRel {m['sq_rel']:.2f} %, "
                f"iRMSE {m['irmse']:.2f}, RMSE {m['rmse'] / 1000:.2f} m, "
                f"delta<1.25 {m['delta1']:.2f} %"
            )
    if "clip" in result:
        print("raw clip with --track:", json.dumps(result["clip"]))
    if args.steps:
        result["real_by_step"] = by_step = {}
        for step in args.steps:
            by_step[step] = score_real(args.workdir, args.samples, out / f"step_{step}", step)
            by_step[step].pop("_frames")
        by_step[r["weights"]] = r
        print_spread(by_step)
    if args.json:
        args.json.write_text(json.dumps(result, indent=2, default=float) + "\n")


def print_spread(by_step: dict) -> None:
    """Real-frame figures of several checkpoints of one run: each, then mean and range."""
    rows = {
        "2d@0.7": lambda r: r["ap40"]["2d@0.7"][1],
        "2d@0.5": lambda r: r["ap40"]["2d@0.5"][1],
        "3d@0.5": lambda r: r["ap40"]["3d@0.5"][1],
        "false positives per frame": lambda r: r["false_positives_per_frame"],
        "found@0.5": lambda r: r["found_iou50"],
        "found@0.7": lambda r: r["found_iou70"],
        "2D width ratio": lambda r: r["box_scale"]["width"],
        "2D height ratio": lambda r: r["box_scale"]["height"],
        "depth ratio": lambda r: r["box_scale"]["depth"],
    }
    print(f"\nreal frames over {len(by_step)} checkpoints (Car moderate):")
    for name, get in rows.items():
        values = np.array([get(r) for r in by_step.values()], np.float64)
        each = ", ".join(f"{v:.2f}" for v in values)
        print(
            f"  {name}: mean {values.mean():.2f}, range {values.min():.2f}-{values.max():.2f} "
            f"({each})"
        )


if __name__ == "__main__":
    main()
