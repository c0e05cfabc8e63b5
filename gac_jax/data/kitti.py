"""KITTI 3D-object format: calibration, labels, result files and the folder layout.

Layout of a KITTI object root (real or generated)::

    ROOT/training/image_2/NNNNNN.png   left colour image
    ROOT/training/image_3/NNNNNN.png   right colour image (optional)
    ROOT/training/calib/NNNNNN.txt     P0..P3, R0_rect, Tr_velo_to_cam (:mod:`kitti_calib`)
    ROOT/training/label_2/NNNNNN.txt   15 columns per object (DontCare included)
    ROOT/training/planes/NNNNNN.txt    ground plane (optional; the AVOD-style files)
    ROOT/ImageSets/{train,val,...}.txt frame ids, one per line

Result files use the label format plus a 16th ``score`` column.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import numpy as np

from gac_jax import geometry
from gac_jax.data.files import KittiFormatError, atomic_write, read_bytes

# Calibration files of every KITTI format (gac_jax.data.kitti_calib), importable from here too.
from gac_jax.data.kitti_calib import Calibration as Calibration
from gac_jax.data.kitti_calib import format_calib as format_calib
from gac_jax.data.kitti_calib import parse_calib as parse_calib
from gac_jax.data.kitti_calib import read_calib as read_calib
from gac_jax.data.kitti_calib import write_calib as write_calib


def parse_plane(text: str, path: str | os.PathLike = "<plane>") -> np.ndarray:
    """Parses a KITTI-format ``planes/NNNNNN.txt`` file -> (4,) float64 normalised plane.

    The file (as AVOD and others distribute for KITTI) is::

        # Plane
        Width 4
        Height 1
        -7.051729e-03 -9.997791e-01 -1.980151e-02 1.680367e+00

    ``a x + b y + c z + d = 0`` in the rectified camera frame. Comment (``#``) lines and the
    ``Width 4`` / ``Height 1`` header are optional; exactly one row of 4 numbers is required.
    The result is scaled to a unit normal pointing up (:func:`gac_jax.geometry.normalize_plane`:
    ``b < 0``, ``d`` = camera height), and the camera must be above the plane (``d > 0``).
    """
    rows = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields or fields[0].startswith("#"):
            continue
        if fields[0] in ("Width", "Height"):
            want = "4" if fields[0] == "Width" else "1"
            if fields[1:] != [want]:
                raise KittiFormatError(path, f"expected '{fields[0]} {want}', got {raw!r}", lineno)
            continue
        if len(fields) != 4 or not all(_is_float(f) for f in fields):
            raise KittiFormatError(path, f"expected 4 numbers 'a b c d', got {raw[:60]!r}", lineno)
        rows.append((lineno, np.array([float(f) for f in fields])))
    if len(rows) != 1:
        raise KittiFormatError(path, f"expected one plane row 'a b c d', found {len(rows)}")
    lineno, plane = rows[0]
    try:
        plane = geometry.normalize_plane(plane)
    except ValueError as e:
        raise KittiFormatError(path, str(e), lineno) from None
    if not plane[3] > 0:
        raise KittiFormatError(
            path, f"the camera is not above the plane (d = {plane[3]:g})", lineno
        )
    return plane


def read_plane(path: str | os.PathLike) -> np.ndarray:
    return parse_plane(read_bytes(path, "plane file").decode("utf-8", "replace"), path)


def format_plane(plane: np.ndarray) -> str:
    """Text of a ``planes/NNNNNN.txt`` file for a (4,) plane (the AVOD header included)."""
    values = " ".join(f"{v:.12e}" for v in np.asarray(plane, np.float64).reshape(4))
    return f"# Plane\nWidth 4\nHeight 1\n{values}\n"


def write_plane(path: str | os.PathLike, plane: np.ndarray) -> None:
    with atomic_write(path) as f:
        f.write(format_plane(plane))


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


@dataclasses.dataclass(frozen=True)
class KittiObjects:
    """Objects of one frame as a struct of arrays (N objects).

    Attributes:
      type: (N,) class names, e.g. ``"Car"``, ``"DontCare"``.
      truncated: (N,) float in [0, 1] (-1 for DontCare / unknown).
      occluded: (N,) int 0..3 (-1 unknown).
      alpha: (N,) observation angle, radians.
      bbox: (N, 4) 2D box xyxy in image pixels.
      dimensions: (N, 3) ``(h, w, l)`` metres.
      location: (N, 3) bottom-face centre ``(x, y, z)`` in the camera frame.
      rotation_y: (N,) yaw about the camera y axis.
      score: (N,) detection confidence (NaN for ground-truth labels).
    """

    type: np.ndarray
    truncated: np.ndarray
    occluded: np.ndarray
    alpha: np.ndarray
    bbox: np.ndarray
    dimensions: np.ndarray
    location: np.ndarray
    rotation_y: np.ndarray
    score: np.ndarray

    def __len__(self) -> int:
        return int(self.type.shape[0])

    @classmethod
    def empty(cls) -> KittiObjects:
        return cls.from_arrays(type=np.zeros((0,), dtype="<U16"))

    @classmethod
    def predictions(cls, **fields) -> KittiObjects:
        """Predicted objects (``type, alpha, bbox, dimensions, location, rotation_y, score``):
        truncation and occlusion unknown (-1), as in KITTI result files."""
        n = len(fields["type"])
        return cls.from_arrays(truncated=np.full(n, -1.0), occluded=np.full(n, -1), **fields)

    @classmethod
    def from_arrays(cls, **fields) -> KittiObjects:
        """Builds objects from any subset of fields; missing ones get KITTI's "unknown" values."""
        n = len(fields["type"])
        defaults = {
            "truncated": np.zeros(n),
            "occluded": np.zeros(n, dtype=np.int64),
            "alpha": np.full(n, -10.0),
            "bbox": np.zeros((n, 4)),
            "dimensions": np.zeros((n, 3)),
            "location": np.zeros((n, 3)),
            "rotation_y": np.zeros(n),
            "score": np.full(n, np.nan),
        }
        defaults.update(fields)
        return cls(
            type=np.asarray(defaults["type"], dtype="<U16").reshape(n),
            truncated=np.asarray(defaults["truncated"], dtype=np.float64).reshape(n),
            occluded=np.asarray(defaults["occluded"], dtype=np.int64).reshape(n),
            alpha=np.asarray(defaults["alpha"], dtype=np.float64).reshape(n),
            bbox=np.asarray(defaults["bbox"], dtype=np.float64).reshape(n, 4),
            dimensions=np.asarray(defaults["dimensions"], dtype=np.float64).reshape(n, 3),
            location=np.asarray(defaults["location"], dtype=np.float64).reshape(n, 3),
            rotation_y=np.asarray(defaults["rotation_y"], dtype=np.float64).reshape(n),
            score=np.asarray(defaults["score"], dtype=np.float64).reshape(n),
        )

    def select(self, index) -> KittiObjects:
        """Subset by boolean mask or integer indices."""
        return KittiObjects(
            **{f.name: getattr(self, f.name)[index] for f in dataclasses.fields(self)}
        )

    def replace(self, **changes) -> KittiObjects:
        return dataclasses.replace(self, **changes)

    @staticmethod
    def concatenate(items: list[KittiObjects]) -> KittiObjects:
        if not items:
            return KittiObjects.empty()
        return KittiObjects(
            **{
                f.name: np.concatenate([getattr(o, f.name) for o in items])
                for f in dataclasses.fields(KittiObjects)
            }
        )


_NUMERIC_FIELDS = (
    "truncated",
    "occluded",
    "alpha",
    "x1",
    "y1",
    "x2",
    "y2",
    "h",
    "w",
    "l",
    "x",
    "y",
)
_NUMERIC_FIELDS = _NUMERIC_FIELDS + ("z", "rotation_y", "score")


def parse_label(
    text: str, path: str | os.PathLike = "<label>", with_score: bool | None = None
) -> KittiObjects:
    """Parses a KITTI label (15 columns) or result (16 columns, score last) file.

    Args:
      with_score: True requires 16 columns, False requires 15, None accepts
        either (per file: all lines must agree).
    """
    rows: list[tuple[str, list[float]]] = []
    ncols_seen = None
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        n = len(fields)
        allowed = {True: (16,), False: (15,), None: (15, 16)}[with_score]
        if n not in allowed:
            want = " or ".join(str(a) for a in allowed)
            raise KittiFormatError(path, f"expected {want} columns, found {n}", lineno)
        if ncols_seen is not None and n != ncols_seen:
            raise KittiFormatError(
                path, f"lines have different column counts ({ncols_seen} and {n})", lineno
            )
        ncols_seen = n
        values = []
        for name, f in zip(_NUMERIC_FIELDS, fields[1:], strict=False):
            try:
                v = float(f)
            except ValueError:
                raise KittiFormatError(
                    path, f"field '{name}': non-numeric value {f!r}", lineno
                ) from None
            if math.isnan(v) or math.isinf(v):
                raise KittiFormatError(path, f"field '{name}': value {f!r} is not finite", lineno)
            values.append(v)
        if fields[0] != "DontCare":
            h, w, l = values[7:10]
            if min(h, w, l) < 0:
                raise KittiFormatError(
                    path, f"negative 3D size (h, w, l) = ({h}, {w}, {l})", lineno
                )
        rows.append((fields[0], values))
    if not rows:
        return KittiObjects.empty()
    types = [r[0] for r in rows]
    arr = np.array([r[1] for r in rows], dtype=np.float64)
    score = arr[:, 14] if arr.shape[1] == 15 else np.full(len(rows), np.nan)
    return KittiObjects.from_arrays(
        type=types,
        truncated=arr[:, 0],
        occluded=arr[:, 1].astype(np.int64),
        alpha=arr[:, 2],
        bbox=arr[:, 3:7],
        dimensions=arr[:, 7:10],
        location=arr[:, 10:13],
        rotation_y=arr[:, 13],
        score=score,
    )


def read_label(path: str | os.PathLike, with_score: bool | None = False) -> KittiObjects:
    """Reads ``label_2/NNNNNN.txt`` (``with_score=False``) or a result file (``True``)."""
    return parse_label(read_bytes(path, "label file").decode("utf-8", "replace"), path, with_score)


def format_label(objects: KittiObjects, with_score: bool | None = None) -> str:
    """KITTI text for ``objects``; scores are written if ``with_score`` (default: if any is set)."""
    if with_score is None:
        with_score = bool(len(objects)) and not np.all(np.isnan(objects.score))
    # One format per line over Python floats (tolist: the same values as the array
    # elements, formatted alike, without indexing numpy arrays field by field).
    line = "{} {:.2f} {} {:.6f} " + "{:.2f} " * 4 + " ".join(["{:.6f}"] * 7)
    columns = [
        objects.type.tolist(),
        objects.truncated.tolist(),
        [int(v) for v in objects.occluded.tolist()],
        objects.alpha.tolist(),
        *np.asarray(objects.bbox).T.tolist(),
        *np.asarray(objects.dimensions).T.tolist(),
        *np.asarray(objects.location).T.tolist(),
        objects.rotation_y.tolist(),
    ]
    if with_score:
        line += " {:.6f}"
        columns.append(objects.score.tolist())
    line += "\n"
    return "".join(line.format(*row) for row in zip(*columns, strict=True))


def write_label(
    path: str | os.PathLike, objects: KittiObjects, with_score: bool | None = None
) -> None:
    """Atomically writes a label or result file."""
    with atomic_write(path) as f:
        f.write(format_label(objects, with_score))


def read_split(path: str | os.PathLike) -> list[str]:
    """Reads an ``ImageSets/*.txt`` file: one frame id per line (blank lines ignored)."""
    ids = []
    for lineno, raw in enumerate(read_bytes(path, "split file").decode().splitlines(), start=1):
        s = raw.strip()
        if not s:
            continue
        if not s.isdigit():
            raise KittiFormatError(path, f"frame id must be digits, got {s!r}", lineno)
        ids.append(s)
    return ids


def write_split(path: str | os.PathLike, ids: list[str]) -> None:
    with atomic_write(path) as f:
        f.write("".join(f"{i}\n" for i in ids))


@dataclasses.dataclass(frozen=True)
class KittiRoot:
    """A KITTI root folder: ``root/training`` (or ``root/testing``) holds the data."""

    root: Path
    subset: str = "training"

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    @property
    def frames_dir(self) -> Path:
        return self.root / self.subset


@dataclasses.dataclass(frozen=True)
class KittiObjectLayout(KittiRoot):
    """Paths of a KITTI object root. ``root/training`` (or ``root/testing``) holds the frames."""

    def image(self, frame_id: str, camera: int = 2) -> Path:
        return self.frames_dir / f"image_{camera}" / f"{frame_id}.png"

    def calib(self, frame_id: str) -> Path:
        return self.frames_dir / "calib" / f"{frame_id}.txt"

    def label(self, frame_id: str) -> Path:
        return self.frames_dir / "label_2" / f"{frame_id}.txt"

    def plane(self, frame_id: str) -> Path:
        return self.frames_dir / "planes" / f"{frame_id}.txt"

    def split_file(self, split: str) -> Path:
        return self.root / "ImageSets" / f"{split}.txt"

    def frame_ids(self, split: str | None = None) -> list[str]:
        """Ids listed in ``ImageSets/<split>.txt``, or of every calib file if ``split`` is None."""
        if split is not None:
            return read_split(self.split_file(split))
        calib_dir = self.frames_dir / "calib"
        if not calib_dir.is_dir():
            raise KittiFormatError(calib_dir, "calibration folder not found")
        return sorted(p.stem for p in calib_dir.glob("*.txt"))
