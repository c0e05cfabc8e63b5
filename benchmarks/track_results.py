"""Objects over time on held-out generated clips: the 3D tracker against its two baselines.

    python benchmarks/track_results.py --workdir W [--out DIR] [--sequences 20]
        [--frames 100] [--seed 7] [--methods kalman3d,sort2d,new_ids] [--runtime jax]
        [--score-threshold S] [--workers N] [--skip-evaluator]

1. Generates the clips (``python -m gac_jax.data.synthetic --sequences N
   --frames-per-sequence F --seed S --out DIR/clips``; resumable, a no-op when complete).
   Use a seed the detector was not trained on.
2. Runs the trained detector of ``W`` (:class:`gac_jax.api.Detector3D`) over every frame:
   ``DIR/detections/SSSS/NNNNNN.txt`` (KITTI result lines; frames already there are skipped).
3. Runs each tracker (``kalman3d``: :class:`gac_jax.tracking.Tracker`, world frame with the
   clips' poses; ``sort2d``: 2D IoU, SORT style; ``new_ids``: a new id per detection, i.e.
   per-frame detection) with the workdir config's ``track`` parameters:
   ``DIR/results/<method>/SSSS.txt`` (KITTI tracking result format) and
   ``DIR/metrics/<method>/SSSS.json``; a sequence already done is skipped.
4. Scores each method with ``python evaluate.py --task track --label-dir
   DIR/clips/training/label_02 --result-dir DIR/results/<method> --json
   DIR/evaluation/<method>.json`` (HOTA, DetA, AssA, LocA, MOTA, MOTP, IDF1, IDSW, Frag,
   MT/ML per class), and computes here, matching each reported box to the ground truth of its
   frame by 2D IoU >= 0.5 (Hungarian): the depth and bird's-eye-view centre errors of the
   reported 3D boxes, the velocity error over the ground (true velocity: the labelled track's
   centres mapped to the world by the poses, differenced over consecutive frames), and
   identity switches of ground-truth tracks per 100 frames.
5. Prints a markdown table (one row per method) and writes ``DIR/track_results.json``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from machine_info import describe_machine, one_line  # benchmarks/ is on sys.path
from scipy.optimize import linear_sum_assignment

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from gac_jax.data.files import atomic_write  # noqa: E402
from gac_jax.data.kitti import KittiObjects, read_label, write_label  # noqa: E402
from gac_jax.data.kitti_tracking import KittiTrackingLayout  # noqa: E402
from gac_jax.detection.nms import box_iou_matrix  # noqa: E402
from gac_jax.tracking import METHODS, TrackerParams  # noqa: E402
from gac_jax.tracking.poses import to_world  # noqa: E402

MIN_IOU = 0.5
EVALUATOR_FIGURES = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "MOTP", "IDF1", "IDSW", "Frag")
PERCENT_FIGURES = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "MOTP", "IDF1")


def generate_clips(args, root: Path) -> None:
    command = [
        sys.executable, "-m", "gac_jax.data.synthetic", "--sequences", str(args.sequences),
        "--frames-per-sequence", str(args.frames), "--seed", str(args.seed), "--out", str(root),
    ]  # fmt: skip
    if args.workers:
        command += ["--workers", str(args.workers)]
    subprocess.run(command, check=True, cwd=REPO)


def run_detector(args, layout: KittiTrackingLayout, out: Path) -> None:
    """``out/SSSS/NNNNNN.txt`` for every frame not there yet."""
    todo = [
        (seq, frame)
        for seq in layout.sequences()
        for frame in layout.frames(seq)
        if not (out / seq / f"{frame.frame:06d}.txt").is_file()
    ]
    if not todo:
        return
    from gac_jax.api import Detector3D
    from gac_jax.data.files import read_image

    detector = Detector3D.from_workdir(
        args.workdir, runtime=args.runtime, score_threshold=args.score_threshold
    )
    print(f"detecting {len(todo)} frames with {detector.weights}", flush=True)
    start = time.perf_counter()
    for i, (seq, frame) in enumerate(todo):
        det = detector.predict(read_image(frame.image), frame.P2, frame.plane)
        write_label(out / seq / f"{frame.frame:06d}.txt", det.to_kitti_objects(), True)
        if (i + 1) % 200 == 0:
            rate = (i + 1) / (time.perf_counter() - start)
            print(f"  {i + 1} of {len(todo)} frames ({rate:.1f} frames/s)", flush=True)


def matches(result: KittiObjects, truth: KittiObjects) -> tuple[np.ndarray, np.ndarray]:
    """``(result rows, truth rows)`` paired by 2D IoU >= :data:`MIN_IOU`, same class."""
    if not len(result) or not len(truth):
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    iou = box_iou_matrix(result.bbox, truth.bbox)
    ok = (iou >= MIN_IOU) & (result.type[:, None] == truth.type[None, :])
    rows, cols = linear_sum_assignment(np.where(ok, 1.0 - iou, 2.0))
    keep = ok[rows, cols]
    return rows[keep], cols[keep]


def track_sequence(method: str, params, layout, seq: str, detections: Path):
    """Runs ``method`` over sequence ``seq``: (KITTI tracking lines, metrics dict)."""
    tracker = METHODS[method](params)
    lines: list[str] = []
    depth_err, bev_err, vel_err = [], [], []
    last_id: dict[int, int] = {}
    switches = 0
    world_prev: dict[int, np.ndarray] = {}
    frames = 0
    for frame in layout.frames(seq):
        frames += 1
        det = read_label(detections / seq / f"{frame.frame:06d}.txt", with_score=True)
        pose = frame.pose if method == "kalman3d" else None
        tracks = tracker.update(det, pose=pose, timestamp=frame.frame / 10.0, plane=frame.plane)
        lines += tracks.to_kitti_tracking_lines(frame.frame)
        labels = frame.labels
        real = labels.objects.type != "DontCare"
        truth, truth_ids = labels.objects.select(real), labels.track_ids[real]
        world = to_world(truth.location, frame.pose) if len(truth) else np.zeros((0, 3))
        rows, cols = matches(tracks.to_kitti_objects(), truth)
        for r, c in zip(rows, cols, strict=True):
            gt_id, out_id = int(truth_ids[c]), int(tracks.ids[r])
            delta = tracks.locations[r] - truth.location[c]
            depth_err.append(abs(delta[2]))
            bev_err.append(float(np.hypot(delta[0], delta[2])))
            if gt_id in last_id and last_id[gt_id] != out_id:
                switches += 1
            last_id[gt_id] = out_id
            v = tracks.velocities[r]
            if gt_id in world_prev and np.all(np.isfinite(v)):
                true_v = (world[c] - world_prev[gt_id]) * 10.0
                est = frame.pose[:, :3] @ v
                vel_err.append(float(np.hypot(*(est - true_v)[[0, 2]])))
        world_prev = {int(t): world[i] for i, t in enumerate(truth_ids)}
    metrics = {
        "frames": frames,
        "matched": len(depth_err),
        "depth_errors": depth_err,
        "bev_errors": bev_err,
        "velocity_errors": vel_err,
        "id_switches": switches,
    }
    return lines, metrics


def run_trackers(args, layout, detections: Path, out: Path, params) -> dict:
    summary = {}
    for method in args.methods:
        for seq in layout.sequences():
            result = out / "results" / (method + args.tag) / f"{seq}.txt"
            metric = out / "metrics" / (method + args.tag) / f"{seq}.json"
            if result.is_file() and metric.is_file():
                continue
            lines, metrics = track_sequence(method, params, layout, seq, detections)
            with atomic_write(result) as f:
                f.write("".join(line + "\n" for line in lines))
            with atomic_write(metric) as f:
                json.dump(metrics, f)
        per_seq = [
            json.loads((out / "metrics" / (method + args.tag) / f"{s}.json").read_text())
            for s in layout.sequences()
        ]
        pooled = {k: sum((m[k] for m in per_seq), []) for k in ("depth_errors", "bev_errors")}
        vel = sum((m["velocity_errors"] for m in per_seq), [])
        frames = sum(m["frames"] for m in per_seq)
        summary[method] = {
            "frames": frames,
            "matched": sum(m["matched"] for m in per_seq),
            "depth_error_median_m": _median(pooled["depth_errors"]),
            "bev_error_median_m": _median(pooled["bev_errors"]),
            "velocity_error_median_mps": _median(vel),
            "id_switches_per_100_frames": 100.0 * sum(m["id_switches"] for m in per_seq) / frames,
        }
    return summary


def _median(values) -> float | None:
    return float(np.median(values)) if len(values) else None


def run_evaluator(label_dir: Path, result_dir: Path, json_path: Path) -> dict | None:
    """The tracking evaluator's figures, or None (with a note) when it fails."""
    command = [
        sys.executable, "evaluate.py", "--task", "track", "--label-dir", str(label_dir),
        "--result-dir", str(result_dir), "--json", str(json_path),
    ]  # fmt: skip
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True)
    if done.returncode != 0:
        note = (done.stderr.strip().splitlines() or ["no message"])[-1]
        print(f"note: evaluate.py --task track failed for {result_dir}: {note}", flush=True)
        return None
    print(done.stdout, flush=True)
    return json.loads(json_path.read_text())


def evaluator_figure(report: dict | None, cls: str, name: str):
    """``name`` of class ``cls`` in the evaluator's JSON (``{'car': {name: v}}``), in percent
    for the ratios, else None."""
    if not report:
        return None
    for node in (report.get(cls), report.get(cls.lower())):
        if isinstance(node, dict) and name in node:
            value = node[name]  # fractions in the JSON, percent in the table (as KITTI prints)
            return 100 * value if name in PERCENT_FIGURES and value is not None else value
    return None


def _cell(value, digits: int = 2) -> str:
    if value is None:
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def markdown_table(summary: dict, evaluation: dict, cls: str) -> str:
    head = ["method", *EVALUATOR_FIGURES, "depth err (m)", "BEV err (m)", "vel err (m/s)",
            "ID sw / 100 frames"]  # fmt: skip
    rows = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for method, s in summary.items():
        figures = [  # evaluation and summary share the methods' keys
            _cell(evaluator_figure(evaluation.get(method), cls, k)) for k in EVALUATOR_FIGURES
        ]
        ours = [s["depth_error_median_m"], s["bev_error_median_m"], s["velocity_error_median_mps"],
                s["id_switches_per_100_frames"]]  # fmt: skip
        rows.append("| " + " | ".join([method, *figures, *(_cell(v) for v in ours)]) + " |")
    return "\n".join(rows)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--workdir", required=True, help="trained detector workdir")
    p.add_argument("--out", help="output folder (default W/track_results_s<seed>)")
    p.add_argument("--sequences", type=int, default=20)
    p.add_argument("--frames", type=int, default=100, help="frames per sequence (10 Hz)")
    p.add_argument("--seed", type=int, default=7, help="clip seed (held out from training)")
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--runtime", default="jax")
    p.add_argument("--score-threshold", type=float, default=None)
    p.add_argument("--workers", type=int, default=None, help="clip generation processes")
    p.add_argument("--class", dest="cls", default="Car", help="class of the table")
    p.add_argument("--skip-evaluator", action="store_true", help="no evaluate.py --task track")
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a tracker parameter instead of the workdir config's (track.KEY; repeatable)",
    )
    p.add_argument("--tag", default="", help="suffix of the methods' result folders (--set)")
    args = p.parse_args(argv)
    args.methods = args.methods.split(",")
    unknown = sorted(set(args.methods) - set(METHODS))
    if unknown:
        p.error(f"unknown methods {unknown} (known: {', '.join(METHODS)})")
    if not (Path(args.workdir) / "config.json").is_file():
        p.error(f"{args.workdir}: no config.json (not a training workdir)")
    out = Path(args.out or Path(args.workdir) / f"track_results_s{args.seed}")
    machine = describe_machine("numpy", "scipy")
    print(one_line(machine), flush=True)
    clips = out / "clips"
    generate_clips(args, clips)
    layout = KittiTrackingLayout(clips)
    detections = out / "detections"
    run_detector(args, layout, detections)
    from gac_jax.trained.run_config import load_run_config

    overrides = dict(item.split("=", 1) for item in args.set)
    params = TrackerParams.from_config(
        load_run_config(args.workdir),
        **{k: int(v) if v.lstrip("-").isdigit() else float(v) for k, v in overrides.items()},
    )
    summary = run_trackers(args, layout, detections, out, params)
    evaluation = {}
    if not args.skip_evaluator:
        for method in args.methods:
            evaluation[method] = run_evaluator(
                clips / "training" / "label_02",
                out / "results" / (method + args.tag),
                out / "evaluation" / f"{method}{args.tag}.json",
            )
    table = markdown_table(summary, evaluation, args.cls)
    print(table)
    record = {
        "machine": machine,
        "arguments": {k: v for k, v in vars(args).items()},
        "tracker": params.__dict__,
        "summary": summary,
        "evaluation": evaluation,
        "table": table,
    }
    with atomic_write(out / "track_results.json") as f:
        json.dump(record, f, indent=2, default=str)
    return 0


if __name__ == "__main__":
    sys.exit(main())
