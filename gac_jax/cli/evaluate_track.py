"""``evaluate.py --task track``: KITTI tracking result files against ``label_02`` labels.

    python evaluate.py --task track --label-dir ROOT/training/label_02 --result-dir R \
        [--classes car,pedestrian] [--poses-dir DIR] [--sequences 0000,0003] \
        [--seqmap FILE] [--mot3d-rule ab3dmot|trackeval] [--allow-empty-results] \
        [--frame-rate 10] [--json OUT]
    python evaluate.py --task track --data ROOT --result-dir R ...   # a KITTI tracking root
                                                                     # or a generated clip set

Result files are ``R/SSSS.txt``, one line per tracked object per frame: the 17 label
columns (``frame id type trunc occ alpha x1 y1 x2 y2 h w l x y z ry``) and a score (on every
line, or on none); the output folder of ``python -m gac_jax.cli.predict ... --track``
(results in ``OUT/tracking``) may be given as it is. The sequences and their lengths come from
the seqmap (``--seqmap``, else ``evaluate_tracking.seqmap.*`` beside ``label_02``), else every
labelled sequence with its image count, poses or labels; a line beyond a sequence's length is
refused, and so is a result folder without any line unless ``--allow-empty-results``. A
labelled sequence without a result file has no tracker boxes. Poses (``poses/SSSS.txt``,
found beside ``label_02`` unless ``--poses-dir`` says where) make the velocity error one
over the ground; without, it is relative to the camera. ``--mot3d-rule`` picks how the 3D
MOT block counts: as AB3DMOT's evaluation script (default, the figures papers report) or
with TrackEval's CLEAR (docs/evaluation.md).
"""

from __future__ import annotations

from pathlib import Path

from gac_jax.evaluation.tracking.evaluator import (
    DEFAULT_FRAME_RATE,
    MOT3D_RULES,
    evaluate_tracking,
    format_tracking_table,
    load_tracking_folders,
)
from gac_jax.evaluation.tracking.kitti_rules import TRACKING_CLASSES

TRACK_ONLY_OPTIONS = (
    "poses_dir", "sequences", "frame_rate", "seqmap", "allow_empty_results", "mot3d_rule",
)  # fmt: skip


def add_track_arguments(parser) -> None:
    """The options only ``--task track`` takes (it shares --label-dir, --result-dir,
    --classes, --data and --json)."""
    g = parser.add_argument_group("--task track")
    g.add_argument(
        "--poses-dir", help="folder of poses/SSSS.txt (default: 'poses' beside --label-dir)"
    )
    g.add_argument(
        "--sequences", help="comma-separated sequences to score (default: the seqmap's, or all)"
    )
    g.add_argument(
        "--seqmap",
        help="seqmap file: the sequences to score and their lengths (default: the "
        "evaluate_tracking.seqmap.* beside --label-dir, the training one of several)",
    )
    g.add_argument(
        "--allow-empty-results",
        action="store_true",
        default=None,
        help="score a result folder without any result line (refused otherwise)",
    )
    g.add_argument(
        "--mot3d-rule",
        choices=tuple(MOT3D_RULES),
        help="how the 3D MOT block (sAMOTA, AMOTA, AMOTP, MOTA) counts: 'ab3dmot' (default: "
        "as AB3DMOT's evaluation script, the figures papers report) or 'trackeval' "
        "(TrackEval's CLEAR with the benchmark's rules, as the table above it)",
    )
    g.add_argument(
        "--frame-rate",
        type=float,
        help=f"frames per second, for velocities (default: {DEFAULT_FRAME_RATE:g}, KITTI's)",
    )


def reject_track_arguments(args, parser) -> None:
    """The track-only options with another task are an error, not ignored."""
    given = [n for n in TRACK_ONLY_OPTIONS if getattr(args, n, None) is not None]
    if given:
        parser.error(f"--{given[0].replace('_', '-')} only applies to --task track")


def stream_results(result_dir: Path) -> Path:
    """``result_dir``, or its ``tracking/`` folder when it is the output folder of a
    ``predict ... --track`` run (no ``SSSS.txt`` of its own)."""
    inner = result_dir / "tracking"
    if inner.is_dir() and not any(p.stem.isdigit() for p in result_dir.glob("*.txt")):
        return inner
    return result_dir


def run(args, parser) -> dict:
    """Scores the folders of ``args``, prints the table; returns the result dict."""
    if args.workdir:
        parser.error(
            "--task track scores tracking result files: give --result-dir (and --label-dir "
            "or --data), not --workdir"
        )
    other = [n for n in ("config", "split", "step", "checkpoint") if getattr(args, n, None)]
    if other or args.overrides or args.require_all:
        parser.error("--task track takes no model-mode options and no --require-all")
    if not args.result_dir or not (args.label_dir or args.data):
        parser.error("--task track needs --result-dir and --label-dir (or --data)")
    if args.label_dir and args.data:
        parser.error("--task track takes --label-dir or --data, not both")
    label_dir = Path(args.label_dir) if args.label_dir else Path(args.data) / "training/label_02"
    poses_dir = Path(args.poses_dir) if args.poses_dir else label_dir.parent / "poses"
    classes = tuple(
        c.strip().lower() for c in (args.classes or ",".join(TRACKING_CLASSES)).split(",")
    )
    if not classes or any(c not in TRACKING_CLASSES for c in classes):
        parser.error(f"--classes must be a subset of car,pedestrian, got {args.classes!r}")
    frame_rate = DEFAULT_FRAME_RATE if args.frame_rate is None else args.frame_rate
    if not frame_rate > 0:
        parser.error(f"--frame-rate must be positive, got {args.frame_rate}")
    sequences = [s.strip() for s in args.sequences.split(",")] if args.sequences else None
    result_dir = stream_results(Path(args.result_dir))
    seqs = load_tracking_folders(
        label_dir,
        result_dir,
        sequences,
        poses_dir,
        seqmap=args.seqmap,
        allow_empty=bool(args.allow_empty_results),
    )
    result = evaluate_tracking(seqs, classes, frame_rate, mot3d_rule=args.mot3d_rule or "ab3dmot")
    n_frames = sum(s.n_frames for s in seqs)
    n_res = sum(len(s.results) for s in seqs)
    missing = sum(not s.result_path.is_file() for s in seqs)
    with_poses = sum(s.poses is not None for s in seqs)
    sources = sorted({s.length_source for s in seqs})
    lengths = sources[0] if len(sources) == 1 else "the images, poses or labels of each"
    print(
        f"{len(seqs)} sequences, {n_frames} frames (lengths from {lengths}), {n_res} result "
        f"lines ({result_dir} vs {label_dir}); {missing} sequences without a result file "
        f"(scored as no boxes); poses for {with_poses}"
    )
    print(format_tracking_table(result), end="")
    result["_meta"] = {
        "sequences": [s.name for s in seqs],
        "frames": n_frames,
        "result_lines": n_res,
        "missing_result_files": missing,
        "sequences_with_poses": with_poses,
        "frame_rate": frame_rate,
        "label_dir": str(label_dir),
        "lengths_from": sources,
        "result_dir": str(result_dir),
    }
    return result
