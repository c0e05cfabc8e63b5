"""KITTI-depth layout: raw calibration, frame listing, the ``val_selection_cropped`` set.

Layout of a KITTI-depth root (real or generated)::

    ROOT/data_depth_annotated/{train,val}/<drive>/proj_depth/groundtruth/image_0{2,3}/NNNNNNNNNN.png
    ROOT/raw/<date>/<drive>/image_0{2,3}/data/NNNNNNNNNN.png
    ROOT/raw/<date>/calib_cam_to_cam.txt                (read by :mod:`gac_jax.data.kitti_calib`)
    ROOT/planes/<drive>/NNNNNNNNNN.txt                  (optional: the frame's ground plane)

``<drive>`` is e.g. ``2011_09_26_drive_0001_sync`` and ``<date>`` its first 10
characters. Ground-truth PNGs hold depth in metres x 256 (0 = invalid) on the
rectified image grid of the same camera.

Ground planes are not part of KITTI-depth; the generated multi-rig dataset writes them, and
a user may add their own. A plane file has the KITTI object ``planes/`` format (AVOD,
:func:`gac_jax.data.kitti.parse_plane`): ``a x + b y + c z + d = 0`` in the rectified
camera-0 frame (x right, y down, z forward, metres), the frame that every ``P_rect_0X``
projects from. One file per frame therefore serves both cameras, as KITTI object planes serve
``P2`` and ``P3``; it sits beside ``data_depth_annotated/``, not in a split, because drive
names are unique across splits.

The devkit's ``depth_selection/val_selection_cropped`` set is flat::

    DIR/image/<drive>_image_<frame>_image_0X.png
    DIR/intrinsics/<drive>_image_<frame>_image_0X.txt        (first 9 numbers = K, row-major)
    DIR/groundtruth_depth/<drive>_groundtruth_depth_<frame>_image_0X.png

A *frame list* file selects depth frames, one ``<drive> <frame> <camera>`` per
line (e.g. ``2011_09_26_drive_0001_sync 0000000005 2``).
"""

from __future__ import annotations

import dataclasses
import os
import re
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, atomic_write, read_bytes

CAMERAS = (2, 3)
_DRIVE_RE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_\d{4}_sync$")
_FRAME_RE = re.compile(r"^\d{10}$")


def _is_float(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def drive_date(drive: str) -> str:
    """``'2011_09_26_drive_0001_sync'`` -> ``'2011_09_26'`` (ValueError for other names)."""
    m = _DRIVE_RE.match(drive)
    if m is None:
        raise ValueError(f"not a KITTI raw drive name: {drive!r} (want YYYY_MM_DD_drive_NNNN_sync)")
    return m.group(1)


@dataclasses.dataclass(frozen=True, order=True)
class DepthFrame:
    """One (drive, frame, camera) item of KITTI-depth."""

    drive: str
    frame: str  # 10 digits
    camera: int  # 2 or 3

    @property
    def frame_id(self) -> str:
        """``'<drive>/<frame>'`` (the camera is kept separately in samples)."""
        return f"{self.drive}/{self.frame}"


@dataclasses.dataclass(frozen=True)
class KittiDepthLayout:
    """Paths of a KITTI-depth root (see module docstring)."""

    root: Path

    def __post_init__(self):
        object.__setattr__(self, "root", Path(self.root))

    def split_dir(self, split: str) -> Path:
        return self.root / "data_depth_annotated" / split

    def groundtruth(self, split: str, frame: DepthFrame) -> Path:
        return (
            self.split_dir(split)
            / frame.drive
            / "proj_depth"
            / "groundtruth"
            / f"image_0{frame.camera}"
            / f"{frame.frame}.png"
        )

    def raw_image(self, frame: DepthFrame) -> Path:
        return (
            self.root
            / "raw"
            / drive_date(frame.drive)
            / frame.drive
            / f"image_0{frame.camera}"
            / "data"
            / f"{frame.frame}.png"
        )

    def calib(self, drive: str) -> Path:
        return self.root / "raw" / drive_date(drive) / "calib_cam_to_cam.txt"

    def plane(self, frame: DepthFrame) -> Path:
        """The frame's (optional) ground-plane file; the same for both cameras."""
        return self.root / "planes" / frame.drive / f"{frame.frame}.txt"

    def frames(self, split: str, cameras: tuple[int, ...] = CAMERAS) -> list[DepthFrame]:
        """Every (drive, frame, camera) with a ground-truth PNG and a raw image, camera-major.

        Order: all frames of ``cameras[0]`` sorted by (drive, frame), then those of
        ``cameras[1]``, ... (like the object source: left views, then right views).
        """
        split_dir = self.split_dir(split)
        if not split_dir.is_dir():
            raise KittiFormatError(split_dir, "KITTI-depth split folder not found")
        out = []
        for cam in cameras:
            if cam not in CAMERAS:
                raise ValueError(f"camera must be 2 or 3, got {cam}")
            items = []
            for drive_dir in sorted(p for p in split_dir.iterdir() if p.is_dir()):
                if _DRIVE_RE.match(drive_dir.name) is None:
                    continue
                gt_dir = drive_dir / "proj_depth" / "groundtruth" / f"image_0{cam}"
                if not gt_dir.is_dir():
                    continue
                for png in sorted(gt_dir.glob("*.png")):
                    if _FRAME_RE.match(png.stem) is None:
                        continue
                    f = DepthFrame(drive_dir.name, png.stem, cam)
                    if self.raw_image(f).is_file():
                        items.append(f)
            out.extend(items)
        return out


def read_frame_list(path: str | os.PathLike) -> list[tuple[DepthFrame, int]]:
    """Reads a frame-list file: ``<drive> <frame> <camera>`` per line.

    Returns (frame, line number) pairs so later checks can name the line.
    """
    out = []
    text = read_bytes(path, "frame list").decode("utf-8", "replace")
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields:
            continue
        if len(fields) != 3:
            raise KittiFormatError(
                path, f"expected '<drive> <frame> <camera>', got {raw!r}", lineno
            )
        drive, frame, cam = fields
        if _DRIVE_RE.match(drive) is None:
            raise KittiFormatError(path, f"not a drive name: {drive!r}", lineno)
        if _FRAME_RE.match(frame) is None:
            raise KittiFormatError(path, f"frame must be 10 digits, got {frame!r}", lineno)
        if cam not in ("2", "3"):
            raise KittiFormatError(path, f"camera must be 2 or 3, got {cam!r}", lineno)
        out.append((DepthFrame(drive, frame, int(cam)), lineno))
    return out


def write_frame_list(path: str | os.PathLike, frames: list[DepthFrame]) -> None:
    with atomic_write(path) as f:
        f.write("".join(f"{fr.drive} {fr.frame} {fr.camera}\n" for fr in frames))


@dataclasses.dataclass(frozen=True)
class SelectionItem:
    """One frame of ``val_selection_cropped`` (paths; ``groundtruth`` None in the test set)."""

    name: str  # image file stem, e.g. 2011_09_26_drive_0002_sync_image_0000000005_image_02
    image: Path
    intrinsics: Path
    groundtruth: Path | None


def list_selection(directory: str | os.PathLike) -> list[SelectionItem]:
    """Lists a ``val_selection_cropped`` folder (or the anonymous test set), sorted by name.

    Every image needs an intrinsics file; ground truth is required when the
    folder has a ``groundtruth_depth/`` subfolder.
    """
    d = Path(directory)
    image_dir, intr_dir, gt_dir = d / "image", d / "intrinsics", d / "groundtruth_depth"
    if not image_dir.is_dir():
        raise KittiFormatError(image_dir, "selection image folder not found")
    has_gt = gt_dir.is_dir()
    items = []
    for img in sorted(image_dir.glob("*.png")):
        intr = intr_dir / f"{img.stem}.txt"
        if not intr.is_file():
            raise KittiFormatError(intr, f"intrinsics file for {img.name} not found")
        gt = None
        if has_gt:
            gt = gt_dir / img.name.replace("_image_", "_groundtruth_depth_", 1)
            if not gt.is_file():
                raise KittiFormatError(gt, f"ground truth for {img.name} not found")
        items.append(SelectionItem(img.stem, img, intr, gt))
    return items


def read_selection_intrinsics(path: str | os.PathLike) -> np.ndarray:
    """K (3, 3) float64 from the first 9 numbers of the first line of an intrinsics file."""
    text = read_bytes(path, "intrinsics file").decode("utf-8", "replace")
    lines = text.splitlines()
    fields = lines[0].split() if lines else []
    if len(fields) < 9:
        raise KittiFormatError(path, f"need 9 numbers (K row-major), found {len(fields)}", 1)
    try:
        K = np.array([float(f) for f in fields[:9]], dtype=np.float64).reshape(3, 3)
    except ValueError:
        bad = next(f for f in fields[:9] if not _is_float(f))
        raise KittiFormatError(path, f"non-numeric value {bad!r}", 1) from None
    if not np.all(np.isfinite(K)) or abs(np.linalg.det(K)) < 1e-12:
        raise KittiFormatError(path, "K is singular or not finite", 1)
    return K
