"""Where an image sequence's frames and files are, by its folder's layout: the KITTI
tracking layout, the KITTI raw layout, or a plain folder (:func:`sequence_files`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from gac_jax.data.files import KittiFormatError
from gac_jax.data.kitti_raw import RawDrive
from gac_jax.data.kitti_tracking import KittiTrackingLayout

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


def sequence_images(folder: Path) -> list[Path]:
    """The images (PNG/JPEG) of ``folder``, sorted by name."""
    if not folder.is_dir():
        raise KittiFormatError(folder, "sequence folder not found")
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise KittiFormatError(folder, f"no images ({', '.join(IMAGE_SUFFIXES)}) in this folder")
    return images


@dataclasses.dataclass(frozen=True)
class SequenceFiles:
    """Where an image sequence's frames and files are, by its folder's layout.

    Attributes:
      images: the folder of the frames.
      calib: the calibration the layout names (None: none; with ``layout`` "KITTI raw" the
        day's ``calib_cam_to_cam.txt`` even where it is missing, to be named in the error).
      planes: the folder of per-frame plane files (``<stem>.txt``), or None.
      layout: ``"KITTI tracking"``, ``"KITTI raw"`` or ``"folder"``.
      raw: the KITTI raw drive (:class:`~gac_jax.data.kitti_raw.RawDrive`), or None.
    """

    images: Path
    calib: Path | None
    planes: Path | None
    layout: str
    raw: RawDrive | None = None


def sequence_files(folder: Path, camera: int = 2) -> SequenceFiles:
    """The files of an image sequence ``folder`` (camera ``camera``): in the KITTI tracking
    layout (``folder`` = ``ROOT/training/image_02/SSSS``) ``ROOT/training/calib/SSSS.txt`` and
    ``ROOT/training/planes/SSSS``; in the KITTI raw layout (``folder`` =
    ``DATE/DATE_drive_NNNN_sync`` or its ``image_0N`` or ``image_0N/data``) the frames of
    ``image_0N/data`` and ``DATE/calib_cam_to_cam.txt``; else ``folder/calib.txt`` (if
    present) and no planes."""
    folder = Path(folder)
    located = KittiTrackingLayout.locate(folder)
    if located is not None:
        layout, sequence = located
        planes = layout.plane(sequence, 0).parent
        return SequenceFiles(folder, layout.calib(sequence), planes, "KITTI tracking")
    drive = RawDrive.locate(folder, camera)
    if drive is not None:
        return SequenceFiles(drive.images, drive.calib, None, "KITTI raw", drive)
    calib = folder / "calib.txt"
    return SequenceFiles(folder, calib if calib.is_file() else None, None, "folder")
