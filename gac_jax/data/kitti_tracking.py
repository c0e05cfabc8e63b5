"""KITTI tracking layout: sequences of frames with per-sequence calib, labels and poses.

Layout of a tracking root (KITTI tracking, plus planes and poses)::

    ROOT/training/image_02/SSSS/NNNNNN.png    left colour images (SSSS: 4-digit sequence)
    ROOT/training/calib/SSSS.txt              the sequence's calibration (KITTI tracking's
                                              P0:..P3:, R_rect, Tr_velo_cam, Tr_imu_velo, or
                                              the object format's keys: :mod:`kitti_calib`)
    ROOT/training/label_02/SSSS.txt           labels of every frame, one object a line
    ROOT/training/planes/SSSS/NNNNNN.txt      each frame's ground plane (AVOD format, optional)
    ROOT/training/poses/SSSS.txt              one line per frame: row-major (3, 4) pose (optional)
    ROOT/training/oxts/SSSS.txt               one OXTS packet per frame (KITTI tracking; the
                                              poses where poses/ has none: :mod:`kitti_oxts`)

A label line is ``frame track_id type truncated occluded alpha x1 y1 x2 y2 h w l x y z
rotation_y`` (17 columns). As in KITTI tracking, ``truncated`` is a level: 0 (in the
image), 1 (partly outside, under half), 2 (half or more outside); ``occluded`` is 0, 1, 2;
DontCare regions have track id -1. A pose maps the rectified camera frame of that frame to
the first frame's (KITTI odometry convention): ``X_0 = R X_k + t``.
"""

from __future__ import annotations

import dataclasses
import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from gac_jax.data import kitti
from gac_jax.data.files import KittiFormatError, atomic_write, read_bytes
from gac_jax.data.kitti import KittiObjects
from gac_jax.data.kitti_oxts import camera_poses, read_oxts

TRUNCATION_LEVELS = (0.0, 0.5)  # truncated fraction > 0 -> level 1, >= 0.5 -> level 2


def truncation_level(fraction: np.ndarray) -> np.ndarray:
    """KITTI tracking truncation level (0, 1, 2) of truncated fractions in [0, 1]; -1 stays."""
    f = np.asarray(fraction, np.float64)
    level = np.where(f >= TRUNCATION_LEVELS[1], 2, np.where(f > TRUNCATION_LEVELS[0], 1, 0))
    return np.where(f < 0, -1, level).astype(np.int64)


@dataclasses.dataclass(frozen=True)
class TrackLabels:
    """Labels of one frame: the objects (``truncated`` holds the level) and their track ids."""

    objects: KittiObjects
    track_ids: np.ndarray  # (N,) int, -1 for DontCare


def format_tracking_labels(frame: int, objects: KittiObjects, track_ids: np.ndarray) -> str:
    """Label lines of one frame (``objects.truncated`` is the fraction, written as a level)."""
    levels = truncation_level(objects.truncated)
    text = kitti.format_label(objects.replace(truncated=levels.astype(np.float64)), False)
    lines = []
    for line, level, track in zip(text.splitlines(), levels, track_ids, strict=True):
        name, _, *rest = line.split(" ")
        lines.append(f"{frame} {int(track)} {name} {int(level)} {' '.join(rest)}\n")
    return "".join(lines)


def parse_tracking_labels(text: str, path: str | os.PathLike = "<label>") -> dict[int, TrackLabels]:
    """Parses a ``label_02/SSSS.txt`` file -> frame -> labels (frames without lines absent)."""
    rows: dict[int, list[tuple[int, str]]] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) != 17:
            raise KittiFormatError(path, f"expected 17 columns, found {len(fields)}", lineno)
        try:
            frame, track = int(fields[0]), int(fields[1])
        except ValueError:
            raise KittiFormatError(path, "frame and track id must be integers", lineno) from None
        if frame < 0:
            raise KittiFormatError(path, f"negative frame number {frame}", lineno)
        rows.setdefault(frame, []).append((track, " ".join(fields[2:])))
    out = {}
    for frame, items in rows.items():
        objects = kitti.parse_label("\n".join(line for _, line in items), path, with_score=False)
        out[frame] = TrackLabels(objects, np.array([t for t, _ in items], np.int64))
    return out


def format_poses(poses: np.ndarray) -> str:
    """Text of a ``poses/SSSS.txt`` file for (N, 3, 4) poses."""
    rows = np.asarray(poses, np.float64).reshape(-1, 12)
    return "".join(" ".join(f"{v:.12e}" for v in row) + "\n" for row in rows)


def parse_poses(text: str, path: str | os.PathLike = "<poses>") -> np.ndarray:
    """Parses a poses file -> (N, 3, 4) float64 (one line of 12 numbers per frame)."""
    rows = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) != 12:
            raise KittiFormatError(path, f"expected 12 numbers, found {len(fields)}", lineno)
        try:
            values = [float(f) for f in fields]
        except ValueError:
            raise KittiFormatError(path, "non-numeric value in a pose", lineno) from None
        if not all(math.isfinite(v) for v in values):
            raise KittiFormatError(path, "non-finite value in a pose", lineno)
        rows.append(values)
    return np.array(rows, np.float64).reshape(-1, 3, 4)


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_write(path) as f:
        f.write(text)


@dataclasses.dataclass(frozen=True)
class TrackingFrame:
    """One frame of a sequence, as the reader gives it.

    Attributes:
      sequence: ``SSSS``; frame: its number.
      image: path of the left image.
      P2: (3, 4) the sequence's left projection.
      plane: (4,) ground plane (None without ``planes/``).
      labels: the frame's labels (None without ``label_02/``; empty if it has no line).
      pose: (3, 4) camera-to-world (None without ``poses/`` or ``oxts/``).
    """

    sequence: str
    frame: int
    image: Path
    P2: np.ndarray
    plane: np.ndarray | None
    labels: TrackLabels | None
    pose: np.ndarray | None


@dataclasses.dataclass(frozen=True)
class KittiTrackingLayout(kitti.KittiRoot):
    """Paths of a KITTI tracking root (``root/training`` holds the sequences) and readers."""

    @classmethod
    def locate(cls, image_dir: str | os.PathLike) -> tuple[KittiTrackingLayout, str] | None:
        """``(layout, sequence)`` of a sequence's image folder ``ROOT/<subset>/image_02/SSSS``
        whose calibration is where the layout puts it; None for any other folder."""
        folder = Path(image_dir).resolve()
        if folder.parent.name != "image_02" or not folder.name.isdigit():
            return None
        layout = cls(folder.parents[2], folder.parents[1].name)
        return (layout, folder.name) if layout.calib(folder.name).is_file() else None

    def image(self, sequence: str, frame: int) -> Path:
        return self.frames_dir / "image_02" / sequence / f"{frame:06d}.png"

    def calib(self, sequence: str) -> Path:
        return self.frames_dir / "calib" / f"{sequence}.txt"

    def label(self, sequence: str) -> Path:
        return self.frames_dir / "label_02" / f"{sequence}.txt"

    def plane(self, sequence: str, frame: int) -> Path:
        return self.frames_dir / "planes" / sequence / f"{frame:06d}.txt"

    def poses(self, sequence: str) -> Path:
        return self.frames_dir / "poses" / f"{sequence}.txt"

    def oxts(self, sequence: str) -> Path:
        return self.frames_dir / "oxts" / f"{sequence}.txt"

    def sequences(self) -> list[str]:
        """The sequences (folders of ``image_02``), sorted."""
        images = self.frames_dir / "image_02"
        if not images.is_dir():
            raise KittiFormatError(images, "image folder not found (not a KITTI tracking root)")
        return sorted(p.name for p in images.iterdir() if p.is_dir() and p.name.isdigit())

    def frame_numbers(self, sequence: str) -> list[int]:
        """Frame numbers of a sequence's images, sorted."""
        folder = self.frames_dir / "image_02" / sequence
        if not folder.is_dir():
            raise KittiFormatError(folder, "sequence not found")
        return sorted(int(p.stem) for p in folder.glob("*.png") if p.stem.isdigit())

    def read_P2(self, sequence: str) -> np.ndarray:
        return kitti.read_calib(self.calib(sequence)).P2

    def read_labels(self, sequence: str) -> dict[int, TrackLabels]:
        path = self.label(sequence)
        return parse_tracking_labels(
            read_bytes(path, "label file").decode("utf-8", "replace"), path
        )

    def read_poses(self, sequence: str) -> np.ndarray:
        path = self.poses(sequence)
        return parse_poses(read_bytes(path, "poses file").decode("utf-8", "replace"), path)

    def read_oxts_poses(self, sequence: str) -> np.ndarray:
        """(N, 3, 4) camera poses of ``oxts/SSSS.txt`` (line k: frame k), relative to frame 0,
        through the sequence's calibration (:func:`gac_jax.data.kitti_oxts.camera_poses`)."""
        return camera_poses(read_oxts(self.oxts(sequence)), kitti.read_calib(self.calib(sequence)))

    def sequence_poses(self, sequence: str) -> tuple[np.ndarray, Path] | None:
        """``(poses, file)`` of a sequence: ``poses/SSSS.txt``, else ``oxts/SSSS.txt``;
        None without either."""
        if self.poses(sequence).exists():
            return self.read_poses(sequence), self.poses(sequence)
        if self.oxts(sequence).exists():
            return self.read_oxts_poses(sequence), self.oxts(sequence)
        return None

    def frames(self, sequence: str) -> Iterator[TrackingFrame]:
        """The frames of a sequence in order, with whatever of planes/labels/poses exists
        (poses: :meth:`sequence_poses`)."""
        P2 = self.read_P2(sequence)
        numbers = self.frame_numbers(sequence)
        labels = self.read_labels(sequence) if self.label(sequence).exists() else None
        found = self.sequence_poses(sequence)
        poses = None if found is None else found[0]
        if found is not None and numbers and len(poses) <= numbers[-1]:
            raise KittiFormatError(found[1], f"{len(poses)} poses for frames up to {numbers[-1]}")
        empty = TrackLabels(KittiObjects.empty(), np.zeros(0, np.int64))
        for k in numbers:
            plane_path = self.plane(sequence, k)
            yield TrackingFrame(
                sequence=sequence,
                frame=k,
                image=self.image(sequence, k),
                P2=P2,
                plane=kitti.read_plane(plane_path) if plane_path.exists() else None,
                labels=None if labels is None else labels.get(k, empty),
                pose=None if poses is None else poses[k],
            )
