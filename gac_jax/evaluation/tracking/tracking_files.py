"""KITTI tracking files (``label_02/SSSS.txt`` and tracker results) as flat arrays.

One line per object per frame::

    frame track_id type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y [score]

Labels have 17 columns; the lines of a result file have 17, or all 18 (the score; 1.0 where
it is absent, as the benchmark takes it). ``truncated`` and ``occluded`` are the tracking
benchmark's levels (a fraction is cut to its integer part, as the official evaluation reads
it). DontCare lines carry track id -1; any other line with a negative track id is not an
object.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, read_bytes

LABEL_COLUMNS = 17
RESULT_COLUMNS = (17, 18)
COLUMN_NAMES = (
    "frame", "track id", "type", "truncated", "occluded", "alpha", "x1", "y1", "x2", "y2",
    "h", "w", "l", "x", "y", "z", "rotation_y", "score",
)  # fmt: skip


@dataclasses.dataclass(frozen=True)
class TrackRows:
    """All N lines of one tracking file, in file order.

    Attributes:
      frame: (N,) int64 frame number; track_id: (N,) int64.
      type: (N,) lower-case class names (``"car"``, ``"dontcare"``, ...).
      truncation, occlusion: (N,) int64 levels.
      box2d: (N, 4) float64 image box xyxy (pixels).
      dimensions: (N, 3) float64 ``h, w, l`` (m); location: (N, 3) float64 bottom-face centre
        in the camera frame (x right, y down, z forward, m); rotation_y: (N,) float64 yaw (rad).
      score: (N,) float64 (1.0 for labels and score-less results).
      line: (N,) int64 line number of each row in its file (from 1), for messages.
    """

    frame: np.ndarray
    track_id: np.ndarray
    type: np.ndarray
    truncation: np.ndarray
    occlusion: np.ndarray
    box2d: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray
    line: np.ndarray

    def __len__(self) -> int:
        return int(self.frame.shape[0])

    def take(self, index: np.ndarray) -> TrackRows:
        """The rows at ``index`` (an int or bool array over the N rows)."""
        return TrackRows(*(getattr(self, f.name)[index] for f in dataclasses.fields(self)))

    def boxes3d(self) -> np.ndarray:
        """(N, 7) ``x, y, z, h, w, l, ry`` boxes (the layout of :mod:`..rotated_iou`)."""
        return np.concatenate([self.location, self.dimensions, self.rotation_y[:, None]], axis=1)

    def has_3d(self) -> np.ndarray:
        """(N,) True where the line carries a 3D box (positive dimensions, finite location)."""
        return (self.dimensions > 0).all(axis=1) & (self.location > -999.0).all(axis=1)


def _first_bad_number(rows: list[list[str]], linenos: list[int], path) -> KittiFormatError:
    """The error of the first field in file order (line, then column) that is not a finite
    number, among the numeric columns (all but the class)."""
    for fields, lineno in zip(rows, linenos, strict=True):
        for col, value in enumerate(fields):
            if col == 2:
                continue
            try:
                finite = np.isfinite(float(value))
            except ValueError:
                finite = None
            if not finite:
                what = "non-numeric" if finite is None else "non-finite"
                problem = f"{what} value {value!r} in column {col + 1} ({COLUMN_NAMES[col]})"
                return KittiFormatError(path, problem, lineno)
    raise AssertionError("no bad field")  # only called when the conversion failed


def parse_tracking_rows(
    text: str, path: str | os.PathLike = "<tracking>", with_score: bool = False
) -> TrackRows:
    """Parses the text of a label (``with_score=False``: 17 columns) or result file.

    Every line of a result file has the column count of its first line (17, or 18 with a
    score), as the official evaluation reads a file: a line that lost or gained a column is
    refused, not read with shifted fields. Raises :class:`KittiFormatError` naming the line
    (and the column of a value that is not a finite number).
    """
    allowed = RESULT_COLUMNS if with_score else (LABEL_COLUMNS,)
    rows, linenos = [], []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) not in allowed:
            want = " or ".join(str(n) for n in allowed)
            raise KittiFormatError(path, f"expected {want} columns, found {len(fields)}", lineno)
        if rows and len(fields) != len(rows[0]):
            raise KittiFormatError(
                path,
                f"{len(fields)} columns, but line {linenos[0]} has {len(rows[0])} (every line "
                "of a result file has the same count: 17, or 18 with a score)",
                lineno,
            )
        rows.append(fields)
        linenos.append(lineno)
    if not rows:
        return _empty_rows()
    if len(rows[0]) == LABEL_COLUMNS:
        for fields in rows:
            fields.append("1")
    numeric_cols = [0, 1, *range(3, 18)]
    try:
        values = np.array([[f[i] for i in numeric_cols] for f in rows], dtype=np.float64)
    except ValueError:
        raise _first_bad_number(rows, linenos, path) from None
    if not np.isfinite(values).all():
        raise _first_bad_number(rows, linenos, path)
    frame, track = values[:, 0], values[:, 1]
    for name, col in (("frame", frame), ("track id", track)):
        bad = np.flatnonzero(col != np.round(col))
        if bad.size:
            raise KittiFormatError(path, f"{name} must be an integer", linenos[bad[0]])
    bad = np.flatnonzero(frame < 0)
    if bad.size:
        raise KittiFormatError(path, f"negative frame number {int(frame[bad[0]])}", linenos[bad[0]])
    return TrackRows(
        frame=frame.astype(np.int64),
        track_id=track.astype(np.int64),
        type=np.array([f[2].lower() for f in rows]),
        truncation=np.trunc(values[:, 2]).astype(np.int64),
        occlusion=np.trunc(values[:, 3]).astype(np.int64),
        box2d=values[:, 5:9].copy(),
        dimensions=values[:, 9:12].copy(),
        location=values[:, 12:15].copy(),
        rotation_y=values[:, 15].copy(),
        score=values[:, 16].copy(),
        line=np.array(linenos, np.int64),
    )


def _empty_rows() -> TrackRows:
    i, f = np.zeros(0, np.int64), np.zeros(0, np.float64)
    box, vec = np.zeros((0, 4)), np.zeros((0, 3))
    return TrackRows(i, i, np.zeros(0, "<U1"), i, i, box, vec, vec, f, f, i)


def check_frames(rows: TrackRows, n_frames: int, path: str | os.PathLike, source: str) -> None:
    """Refuses a row whose frame is not in ``0 .. n_frames - 1`` (``source``: where the
    sequence's length comes from, for the message), as the official evaluation does."""
    bad = np.flatnonzero(rows.frame >= n_frames)
    if bad.size:
        k = bad[0]
        raise KittiFormatError(
            path,
            f"frame {int(rows.frame[k])} is beyond the sequence's {n_frames} frames ({source})",
            int(rows.line[k]),
        )


def read_tracking_file(path: str | os.PathLike, with_score: bool = False) -> TrackRows:
    """Reads a label (``with_score=False``) or result file; see :func:`parse_tracking_rows`."""
    what = "result file" if with_score else "label file"
    text = read_bytes(path, what).decode("utf-8", "replace")
    return parse_tracking_rows(text, path, with_score)


def sequence_files(folder: str | os.PathLike, what: str) -> dict[str, Path]:
    """``{SSSS: path}`` of the ``SSSS.txt`` files (numeric names) of a folder, sorted by name."""
    folder = Path(folder)
    if not folder.is_dir():
        raise KittiFormatError(folder, f"{what} folder not found")
    files = {p.stem: p for p in folder.glob("*.txt") if p.stem.isdigit()}
    return dict(sorted(files.items()))
