"""Command line of ``evaluate.py``: score result folders against KITTI ground truth (offline mode).

    python evaluate.py --task detect3d --label-dir L --result-dir R [--split-file F] [--json OUT]
    python evaluate.py --task depth --groundtruth-dir G --prediction-dir P [--json OUT]
    python evaluate.py --task detect3d --workdir W [--step N] ...   # model mode, see
        gac_jax/cli/evaluate_detector.py
    python evaluate.py --task depth --workdir W [--data DIR] [--split S] [--step N] [--out DIR]
    python evaluate.py --task depth --baseline {ground-plane,row-mean} (--data DIR | --workdir W)
    python evaluate.py --task track --label-dir L --result-dir R [--classes car,pedestrian] ...
        # KITTI tracking: HOTA, CLEAR MOT, IDF1, sAMOTA; see gac_jax/cli/evaluate_track.py

The offline scorers are plain functions returning the result dict
(:func:`evaluate_detection_folders`, :func:`evaluate_depth_folders`); a mode that
first runs a trained model (writing result files) plugs in beside them in
:func:`main` and reuses them for scoring. Invalid input ends with a one-line
``error: <file>[:<line>]: <problem>`` on stderr and exit code 2, and so does a workdir that
another process writes to (model mode writes its results there: it holds the workdir's lock,
:mod:`gac_jax.training.workdir_lock`); a full disk ends with ``error: <file>: no space left on
device (N MB free)`` and exit code 1.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path

from gac_jax.cli import evaluate_track
from gac_jax.cli.evaluate_track import add_track_arguments, reject_track_arguments
from gac_jax.cli.model_mode import add_model_mode_arguments, reject_model_mode_arguments
from gac_jax.data.files import KittiFormatError, atomic_write, read_depth_png
from gac_jax.data.io_errors import error_line, exit_code
from gac_jax.data.kitti import KittiObjects, read_label, read_split
from gac_jax.evaluation.ap_table import format_table, overlap_meta
from gac_jax.evaluation.depth_metrics import DepthMetricAccumulator, format_depth_table
from gac_jax.evaluation.kitti_object import CLASSES, evaluate_detections
from gac_jax.training.workdir_lock import WorkdirBusyError

EXIT_INVALID_INPUT = 2


def detection_frame_ids(label_dir: Path, split_file: str | os.PathLike | None) -> list[str]:
    """Frame ids of the evaluation: the split file's, or the stem of every ``*.txt`` label."""
    if split_file is not None:
        ids = read_split(split_file)
        if not ids:
            raise KittiFormatError(split_file, "split file lists no frame")
        return ids
    ids = sorted(p.stem for p in label_dir.glob("*.txt"))
    if not ids:
        raise KittiFormatError(label_dir, "no label files (*.txt) found")
    return ids


def load_detection_folders(
    label_dir: str | os.PathLike,
    result_dir: str | os.PathLike,
    split_file: str | os.PathLike | None = None,
) -> tuple[list[str], list[KittiObjects], list[KittiObjects]]:
    """Reads labels and results: (frame ids, ground truth per frame, detections per frame).

    A frame without a result file has no detections; a listed frame without a
    label file, or any malformed file, raises :class:`KittiFormatError`.
    """
    label_dir, result_dir = Path(label_dir), Path(result_dir)
    if not label_dir.is_dir():
        raise KittiFormatError(label_dir, "label folder not found")
    if not result_dir.is_dir():
        raise KittiFormatError(result_dir, "result folder not found")
    ids = detection_frame_ids(label_dir, split_file)
    gts, dts = [], []
    for frame_id in ids:
        gts.append(read_label(label_dir / f"{frame_id}.txt", with_score=False))
        result = result_dir / f"{frame_id}.txt"
        dts.append(read_label(result, with_score=True) if result.exists() else KittiObjects.empty())
    return ids, gts, dts


def missing_result_ids(result_dir: str | os.PathLike, frame_ids: Sequence[str]) -> list[str]:
    """The frame ids of ``frame_ids`` without a result file ``<result_dir>/<id>.txt``."""
    result_dir = Path(result_dir)
    return [i for i in frame_ids if not (result_dir / f"{i}.txt").exists()]


def evaluate_detection_folders(
    label_dir: str | os.PathLike,
    result_dir: str | os.PathLike,
    split_file: str | os.PathLike | None = None,
    classes: Sequence[str] = CLASSES,
) -> dict:
    """KITTI AP of a result folder (``NNNNNN.txt``, 16 columns) against a ``label_2`` folder.

    Returns the dict of :func:`gac_jax.evaluation.kitti_object.evaluate_detections`.
    """
    _, gts, dts = load_detection_folders(label_dir, result_dir, split_file)
    return evaluate_detections(gts, dts, classes=classes)


def evaluate_depth_folders(
    groundtruth_dir: str | os.PathLike, prediction_dir: str | os.PathLike
) -> tuple[dict[str, float], int]:
    """Mean KITTI depth metrics of 16-bit PNG predictions vs ground truth at the same paths.

    Every ``*.png`` under ``groundtruth_dir`` (recursively) needs a prediction
    of the same size at the same relative path under ``prediction_dir``.

    Returns:
      (metrics dict keyed by ``DEPTH_METRICS``, number of images).
    """
    gt_root, pred_root = Path(groundtruth_dir), Path(prediction_dir)
    if not gt_root.is_dir():
        raise KittiFormatError(gt_root, "ground-truth folder not found")
    if not pred_root.is_dir():
        raise KittiFormatError(pred_root, "prediction folder not found")
    gt_files = sorted(p.relative_to(gt_root) for p in gt_root.rglob("*.png"))
    if not gt_files:
        raise KittiFormatError(gt_root, "no ground-truth PNG files found")
    acc = DepthMetricAccumulator()
    for rel in gt_files:
        pred_path = pred_root / rel
        if not pred_path.is_file():
            raise KittiFormatError(pred_path, f"prediction missing for ground truth {rel}")
        gt = read_depth_png(gt_root / rel)
        pred = read_depth_png(pred_path)
        if pred.shape != gt.shape:
            raise KittiFormatError(
                pred_path,
                f"prediction is {pred.shape[1]}x{pred.shape[0]} but the ground truth is "
                f"{gt.shape[1]}x{gt.shape[0]} (width x height)",
            )
        try:
            acc.update(pred, gt)
        except ValueError as e:
            bad = gt_root / rel if "ground truth has no valid" in str(e) else pred_path
            raise KittiFormatError(bad, str(e)) from None
    return acc.result(), acc.count


def _write_json(path: str | os.PathLike, payload: dict) -> None:
    with atomic_write(path) as f:
        json.dump(payload, f, indent=2)
        f.write("\n")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="evaluate.py",
        description="KITTI evaluation: 3D object detection AP (2D/BEV/3D/AOS, R11 and R40), "
        "depth prediction metrics, or tracking (HOTA, CLEAR MOT, IDF1, 3D MOT), from files "
        "on disk.",
    )
    parser.add_argument("--task", required=True, choices=("detect3d", "depth", "track"))
    parser.add_argument("--json", metavar="OUT", help="also write the result dict as JSON")
    det = parser.add_argument_group("--task detect3d")
    det.add_argument(
        "--label-dir", help="folder of KITTI label files NNNNNN.txt (label_2; track: label_02)"
    )
    det.add_argument(
        "--result-dir", help="folder of result files NNNNNN.txt (16 columns; track: SSSS.txt)"
    )
    det.add_argument("--split-file", help="frame ids to evaluate (default: every label file)")
    det.add_argument(
        "--classes",
        help="comma-separated subset of Car,Pedestrian,Cyclist (default: all three; "
        "--task track: of car,pedestrian, default both)",
    )
    det.add_argument(
        "--require-all",
        action="store_true",
        help="fail if a frame of the label folder (or split file) has no result file "
        "(default: such a frame counts as 'no detections', and the count is printed)",
    )
    dep = parser.add_argument_group("--task depth")
    dep.add_argument("--groundtruth-dir", help="folder of 16-bit ground-truth depth PNGs")
    dep.add_argument("--prediction-dir", help="folder of 16-bit predicted depth PNGs (same paths)")
    # Depth model mode (gac_jax/cli/evaluate_depth.py); --workdir, --data, --split and
    # --step are the shared model-mode options below.
    dep.add_argument(
        "--baseline",
        choices=("ground-plane", "row-mean"),
        help="score a no-learning baseline (row-mean: fitted on the train split of the data)",
    )
    dep.add_argument("--out", help="folder for the predicted 16-bit PNGs")
    add_track_arguments(parser)
    add_model_mode_arguments(parser)
    return parser


def _run_detect3d(args, parser) -> dict:
    if args.workdir and args.require_all:
        parser.error("--require-all applies to offline mode (--label-dir/--result-dir)")
    if args.workdir:
        from gac_jax.cli.evaluate_detector import run_model_mode

        return run_model_mode(args, parser)
    reject_model_mode_arguments(args, parser)
    if not args.label_dir or not args.result_dir:
        parser.error("--task detect3d needs --label-dir and --result-dir")
    classes = tuple(c.strip() for c in (args.classes or ",".join(CLASSES)).split(",") if c.strip())
    unknown = [c for c in classes if c not in CLASSES]
    if unknown or not classes:
        parser.error(f"--classes must be a subset of {','.join(CLASSES)}, got {args.classes!r}")
    ids, gts, dts = load_detection_folders(args.label_dir, args.result_dir, args.split_file)
    missing = missing_result_ids(args.result_dir, ids)
    if missing and args.require_all:
        raise KittiFormatError(
            args.result_dir,
            f"{len(missing)} of {len(ids)} frames have no result file "
            f"(e.g. {missing[0]}.txt); --require-all refuses to score them as no detections",
        )
    result = evaluate_detections(gts, dts, classes=classes)
    n_det = sum(len(d) for d in dts)
    print(f"{len(ids)} frames, {n_det} detections ({args.result_dir} vs {args.label_dir})")
    print(
        f"{len(missing)} of {len(ids)} frames have no result file (scored as no detections"
        + (f"; e.g. {missing[0]}.txt)" if missing else ")")
    )
    print(format_table(result), end="")
    return result


DEPTH_MODEL_MODE_UNSUPPORTED = ("config", "checkpoint", "batch_size", "threads", "overrides")


def _run_depth(args, parser) -> dict:
    if args.require_all:
        parser.error("--require-all applies to --task detect3d (depth already needs every file)")
    if args.workdir or args.baseline:
        unsupported = [n for n in DEPTH_MODEL_MODE_UNSUPPORTED if getattr(args, n, None)]
        if unsupported or args.save_images:
            names = [n.replace("_", "-") for n in unsupported] + (
                ["save-images"] * bool(args.save_images)
            )
            parser.error(f"--task depth model mode does not take --{', --'.join(names)}")
        from gac_jax.cli import evaluate_depth

        return evaluate_depth.run(args)
    reject_model_mode_arguments(args, parser)
    if args.out:
        parser.error("--out only applies with --workdir or --baseline")
    if not args.groundtruth_dir or not args.prediction_dir:
        parser.error("--task depth needs --groundtruth-dir and --prediction-dir")
    metrics, count = evaluate_depth_folders(args.groundtruth_dir, args.prediction_dir)
    print(format_depth_table(metrics, count), end="")
    return metrics


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``evaluate.py``; returns the exit code (0 ok, 1 disk failure, 2 invalid
    input or workdir in use)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.task != "track":
        reject_track_arguments(args, parser)
    runners = {"detect3d": _run_detect3d, "depth": _run_depth, "track": evaluate_track.run}
    try:
        result = runners[args.task](args, parser)
        if args.json:
            if args.task == "detect3d":  # which overlap each (strict/loose) entry used
                result = {**result, "_meta": {"min_overlap": overlap_meta(result)}}
            _write_json(args.json, result)
    except (KittiFormatError, WorkdirBusyError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_INVALID_INPUT
    except OSError as e:
        where = args.json or args.workdir or args.result_dir or args.prediction_dir
        print(f"error: {error_line(e, where)}", file=sys.stderr)
        return exit_code(e)
    return 0
