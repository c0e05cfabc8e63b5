"""KITTI tracking files (``label_02/SSSS.txt`` and tracker results) as flat arrays.

One line per object per frame::

    frame track_id type truncated occluded alpha x1 y1 x2 y2 h w l x y z rotation_y [score]

Labels have 17 columns; a result line has 17 or 18 (the score; 1.0 where it is absent, as
the benchmark takes it). ``truncated`` and ``occluded`` are the tracking benchmark's levels
(a fraction is cut to its integer part, as the official evaluation reads it). DontCare lines
carry track id -1; any other line with a negative track id is not an object.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, read_bytes

LABEL_COLUMNS = 17
RESULT_COLUMNS = (17, 18)


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


def _bad_line(rows: list[list[str]], linenos: list[int], path, columns: slice) -> None:
    for fields, lineno in zip(rows, linenos, strict=True):
        for value in fields[columns]:
            try:
                number = float(value)
            except ValueError:
                raise KittiFormatError(path, f"non-numeric value {value!r}", lineno) from None
            if not np.isfinite(number):
                raise KittiFormatError(path, f"non-finite value {value!r}", lineno)


def parse_tracking_rows(
    text: str, path: str | os.PathLike = "<tracking>", with_score: bool = False
) -> TrackRows:
    """Parses the text of a label (``with_score=False``: 17 columns) or result file."""
    allowed = RESULT_COLUMNS if with_score else (LABEL_COLUMNS,)
    rows, linenos = [], []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) not in allowed:
            want = " or ".join(str(n) for n in allowed)
            raise KittiFormatError(path, f"expected {want} columns, found {len(fields)}", lineno)
        if len(fields) == LABEL_COLUMNS:
            fields.append("1")
        rows.append(fields)
        linenos.append(lineno)
    if not rows:
        return _empty_rows()
    numeric_cols = [0, 1, *range(3, 18)]
    try:
        values = np.array([[f[i] for i in numeric_cols] for f in rows], dtype=np.float64)
    except ValueError:
        _bad_line(rows, linenos, path, slice(3, None))
        _bad_line(rows, linenos, path, slice(0, 2))
        raise
    if not np.isfinite(values).all():
        _bad_line(rows, linenos, path, slice(0, None))
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
    )


def _empty_rows() -> TrackRows:
    i, f = np.zeros(0, np.int64), np.zeros(0, np.float64)
    return TrackRows(
        i, i, np.zeros(0, "<U1"), i, i, np.zeros((0, 4)), np.zeros((0, 3)), np.zeros((0, 3)), f, f
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
