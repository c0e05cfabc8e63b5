"""KITTI tracking evaluation of result folders: HOTA, CLEAR MOT, IDF1 and the 3D MOT block.

:func:`load_tracking_folders` reads a ``label_02`` folder and a folder of result files
(``SSSS.txt``, the label columns plus a score), with the poses of each sequence when there
are; :func:`evaluate_tracking` scores them per class and :func:`format_tracking_table`
prints the table.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, read_bytes
from gac_jax.data.kitti_tracking import parse_poses
from gac_jax.evaluation.tracking.ab3dmot_rules import ab3dmot_metrics
from gac_jax.evaluation.tracking.clear import (
    COUNT_FIELDS as CLEAR_COUNTS,
)
from gac_jax.evaluation.tracking.clear import (
    clear_counts,
    clear_match,
    clear_metrics,
)
from gac_jax.evaluation.tracking.hota import combine_hota, hota_metrics, hota_sums
from gac_jax.evaluation.tracking.identity import COUNT_FIELDS as ID_COUNTS
from gac_jax.evaluation.tracking.identity import identity_counts, identity_metrics
from gac_jax.evaluation.tracking.kitti_rules import CLASS_NAMES, TRACKING_CLASSES, prepare_class
from gac_jax.evaluation.tracking.mot3d import (
    MOT3D_IOUS,
    VelocityErrors,
    mot3d_metrics,
    velocity_errors,
)
from gac_jax.evaluation.tracking.seqmap import find_seqmap, read_seqmap
from gac_jax.evaluation.tracking.tracking_files import (
    TrackRows,
    check_frames,
    read_tracking_file,
    sequence_files,
)

DEFAULT_FRAME_RATE = 10.0  # Hz, KITTI's
# the 3D MOT block's rules: AB3DMOT's own script (the figures papers report; the default) or
# TrackEval's CLEAR counting with the benchmark's rules, as the 2D table above it
MOT3D_RULES = {"ab3dmot": ab3dmot_metrics, "trackeval": mot3d_metrics}
MOT3D_RULE_NAMES = {
    "ab3dmot": "AB3DMOT's script; MOTA at its best score threshold",
    "trackeval": "TrackEval's CLEAR; MOTA of every track",
}


@dataclasses.dataclass(frozen=True)
class TrackingSequence:
    """One sequence: its label and result rows, frame count (and where the count comes from),
    and poses ((n, 3, 4) or None)."""

    name: str
    labels: TrackRows
    results: TrackRows
    n_frames: int
    label_path: Path
    result_path: Path
    poses: np.ndarray | None = None
    length_source: str = ""


def _length(name, labels: TrackRows, label_path: Path, seqmap, poses, pose_path):
    """(number of frames of sequence ``name``, where it comes from): the seqmap's count, else
    the images beside ``label_02`` (``image_02/SSSS``), else the poses, else the labels."""
    if seqmap is not None:
        return seqmap[1][name], f"seqmap {seqmap[0]}"
    images = label_path.parent.parent / "image_02" / name
    numbers = [int(p.stem) for p in images.glob("*.png") if p.stem.isdigit()]
    if numbers:
        return max(numbers) + 1, f"the images in {images}"
    if poses is not None:
        return len(poses), f"the poses of {pose_path}"
    n = int(labels.frame.max(initial=-1)) + 1
    return n, f"the last labelled frame of {label_path}; give the length with a seqmap"


def load_tracking_folders(
    label_dir: str | os.PathLike,
    result_dir: str | os.PathLike,
    sequences: Sequence[str] | None = None,
    poses_dir: str | os.PathLike | None = None,
    seqmap: str | os.PathLike | None = None,
    allow_empty: bool = False,
) -> list[TrackingSequence]:
    """Reads the sequences to score and their result files.

    The sequences are those of the seqmap (``seqmap``, else the ``evaluate_tracking.seqmap.*``
    beside ``label_dir``: :mod:`.seqmap`), else every labelled one; ``sequences`` picks some
    of them. A sequence's length is the seqmap's count, else its image count
    (``image_02/SSSS`` beside ``label_dir``), else its poses' count, else its last labelled
    frame + 1; a label or result line beyond it is refused. A sequence without a result file
    has no tracker boxes; a result folder without any result line is refused unless
    ``allow_empty``. Raises :class:`KittiFormatError` for any of these, a malformed file, a
    result file of a sequence without labels or an unknown sequence in ``sequences``.
    """
    labels = sequence_files(label_dir, "label")
    results = sequence_files(result_dir, "result")
    seqmap_path = Path(seqmap) if seqmap is not None else find_seqmap(label_dir)
    mapped = (seqmap_path, read_seqmap(seqmap_path)) if seqmap_path is not None else None
    if not labels:
        raise KittiFormatError(label_dir, "no label files (SSSS.txt) found")
    orphans = sorted(set(results) - set(labels))
    if orphans:
        raise KittiFormatError(
            results[orphans[0]], f"result file of sequence {orphans[0]}, which has no labels"
        )
    listed = list(mapped[1]) if mapped is not None else list(labels)
    names = listed if sequences is None else list(sequences)
    for name in names:
        if mapped is not None and name not in mapped[1]:
            raise KittiFormatError(seqmap_path, f"sequence {name} is not in this seqmap")
        if name not in labels:
            raise KittiFormatError(
                Path(label_dir) / f"{name}.txt", f"unknown sequence {name} (no label file)"
            )
    out = []
    for name in names:
        rows = read_tracking_file(labels[name])
        result_path = Path(result_dir) / f"{name}.txt"
        res = read_tracking_file(result_path, with_score=True) if name in results else None
        if res is None:
            res = rows.take(np.zeros(0, np.int64))
        poses = None
        pose_path = Path(poses_dir) / f"{name}.txt" if poses_dir is not None else None
        if pose_path is not None and pose_path.is_file():
            poses = parse_poses(read_bytes(pose_path, "poses file").decode("utf-8", "replace"))
        n_frames, source = _length(name, rows, labels[name], mapped, poses, pose_path)
        for path, r in ((labels[name], rows), (result_path, res)):
            check_frames(r, n_frames, path, source)
            if poses is not None:
                check_frames(r, len(poses), path, f"the poses of {pose_path}")
        seq = TrackingSequence(name, rows, res, n_frames, labels[name], result_path, poses, source)
        out.append(seq)
    if not allow_empty and not any(len(s.results) for s in out):
        what = "no result line in" if any(s.result_path.is_file() for s in out) else "no"
        raise KittiFormatError(
            result_dir,
            f"{what} result files (SSSS.txt) of the {len(out)} sequences scored: an empty "
            "result folder scores zero (say it is meant with --allow-empty-results)",
        )
    return out


def _sum(dicts: list[dict], keys) -> dict[str, float]:
    return {k: float(sum(d[k] for d in dicts)) for k in keys}


# the columns of the printed table, and the figures of each sequence in the result dict
SEQUENCE_FIELDS = ("HOTA", "DetA", "AssA", "LocA", "MOTA", "MOTP", "IDF1")
SEQUENCE_FIELDS += ("IDSW", "Frag", "MT", "ML")


def _figures(hota: dict, clear: dict, ident: dict) -> dict:
    out = hota_metrics(hota)
    out.update(clear_metrics(clear))
    out.update(identity_metrics(ident))
    return out


def _sequence_figures(hota: dict, clear: dict, ident: dict) -> dict:
    """``SEQUENCE_FIELDS`` of one sequence; MOTA is None (undefined) without ground truth."""
    out = {k: v for k, v in _figures(hota, clear, ident).items() if k in SEQUENCE_FIELDS}
    if clear["TP"] + clear["FN"] == 0:
        out["MOTA"] = None
    return out


def has_3d(sequences: Sequence[TrackingSequence], cls_names: Sequence[str]) -> bool:
    """True when the ground truth and the results of the classes carry 3D boxes."""
    for attr in ("labels", "results"):
        rows = [getattr(s, attr) for s in sequences]
        flags = np.concatenate([r.has_3d()[np.isin(r.type, cls_names)] for r in rows])
        if flags.size and not flags.any():
            return False
    return True


def evaluate_tracking(
    sequences: Sequence[TrackingSequence],
    classes: Sequence[str] = TRACKING_CLASSES,
    frame_rate: float = DEFAULT_FRAME_RATE,
    with_3d: bool | None = None,
    mot3d_rule: str = "ab3dmot",
) -> dict:
    """KITTI tracking figures per class.

    Returns:
      ``{cls: {HOTA, DetA, AssA, LocA, DetRe, DetPr, AssRe, AssPr, HOTA(0), LocA(0), MOTA,
      MOTP, MODA, sMOTA, CLR_Re, CLR_Pr, CLR_F1, MTR, PTR, MLR, TP, FN, FP, IDSW, MT, PT, ML,
      Frag, IDF1, IDP, IDR, IDTP, IDFN, IDFP, curves, sequences, mot3d, velocity}}`` for each class
      (``"car"``, ``"pedestrian"``), figures in [0, 1] (MOTA may be negative). ``curves``:
      the HOTA figures at each alpha; ``sequences``: ``{SSSS: SEQUENCE_FIELDS}`` (MOTA None
      for a sequence without ground truth of the class). ``mot3d``:
      ``{"0.25": {sAMOTA, AMOTA, AMOTP, MOTA, thresholds, ...}, "0.50": {...}}`` by the rule
      ``mot3d_rule`` (:data:`MOT3D_RULES`: :func:`.ab3dmot_metrics` or
      :func:`.mot3d_metrics`; ``mot3d_rule`` names it), or None without 3D boxes;
      ``velocity``: :class:`VelocityErrors` as a dict, or None.
    """
    mot3d = MOT3D_RULES[mot3d_rule]
    out = {}
    for cls in classes:
        hs, cs, ids, per_seq = [], [], [], []
        for s in sequences:
            paths = {"label_path": s.label_path, "result_path": s.result_path}
            seq = prepare_class(s.labels, s.results, cls, s.n_frames, **paths)
            matched = clear_match(seq)
            hs.append(hota_sums(seq))
            cs.append(clear_counts(seq, matched))
            ids.append(identity_counts(seq))
            per_seq.append((s, seq, matched))
        res = _figures(combine_hota(hs), _sum(cs, CLEAR_COUNTS), _sum(ids, ID_COUNTS))
        res["sequences"] = {
            s.name: _sequence_figures(h, c, i)
            for s, h, c, i in zip(sequences, hs, cs, ids, strict=True)
        }
        use_3d = has_3d(sequences, CLASS_NAMES[cls]) if with_3d is None else with_3d
        res["mot3d"] = (
            {f"{iou:.2f}": mot3d(sequences, cls, iou) for iou in MOT3D_IOUS} if use_3d else None
        )
        res["mot3d_rule"] = mot3d_rule
        vel = [velocity_errors(s, seq, m, frame_rate) for s, seq, m in per_seq] if use_3d else []
        res["velocity"] = VelocityErrors.combine(vel).as_dict() if vel else None
        out[cls] = res
    return out


def format_tracking_table(result: dict) -> str:
    """The KITTI tracking table (percent, as the benchmark prints it) of
    :func:`evaluate_tracking`'s result."""
    head = SEQUENCE_FIELDS
    lines = [f"{'class':<11}" + "".join(f"{h:>8}" for h in head)]
    for cls, r in result.items():
        cells = [f"{100 * r[k]:8.2f}" for k in head[:7]]
        cells += [f"{r[k]:8d}" for k in ("IDSW", "Frag", "MT", "ML")]
        lines.append(f"{cls.capitalize():<11}" + "".join(cells))
    blocks = [(c, r["mot3d"], r.get("mot3d_rule")) for c, r in result.items() if r.get("mot3d")]
    if blocks:
        lines.append("")
        rule = MOT3D_RULE_NAMES.get(blocks[0][2], "")
        head = f"{'3D MOT':<11}{'IoU':>6}{'sAMOTA':>9}{'AMOTA':>9}{'AMOTP':>9}{'MOTA':>9}"
        lines.append(head + (f"   ({rule})" if rule else ""))
        for cls, m, _ in blocks:
            for iou, v in m.items():
                lines.append(
                    f"{cls.capitalize():<11}{iou:>6}"
                    + "".join(
                        f"{'-':>9}" if v[k] is None else f"{100 * v[k]:9.2f}"
                        for k in ("sAMOTA", "AMOTA", "AMOTP", "MOTA")
                    )
                )
    vel = [(c, r["velocity"]) for c, r in result.items() if r.get("velocity")]
    if vel:
        lines.append("")
        lines.append(f"{'velocity':<11}{'frame':>7}{'pairs':>8}{'mean m/s':>10}{'median':>8}")
        for cls, v in vel:  # no matched pair with a velocity: no mean / median
            stats = "".join(
                f"{'-':>{w}}" if v[k] is None else f"{v[k]:{w}.3f}"
                for k, w in (("mean", 10), ("median", 8))
            )
            lines.append(f"{cls.capitalize():<11}{v['frame']:>7}{v['pairs']:>8d}{stats}")
    return "\n".join(lines) + "\n"
