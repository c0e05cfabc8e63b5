"""KITTI raw drives: the folder layout, the frames' timestamps and their OXTS poses.

Layout of a raw recording day, as KITTI ships it::

    DATE/calib_cam_to_cam.txt, calib_velo_to_cam.txt, calib_imu_to_velo.txt   the day's
                                         calibration (:mod:`gac_jax.data.kitti_calib`)
    DATE/DATE_drive_NNNN_sync/image_0N/data/NNNNNNNNNN.png   rectified frames of camera N
    DATE/DATE_drive_NNNN_sync/image_0N/timestamps.txt        one time per frame
    DATE/DATE_drive_NNNN_sync/oxts/data/NNNNNNNNNN.txt       one OXTS packet per frame
                                                             (:mod:`gac_jax.data.kitti_oxts`)

A timestamp line is ``YYYY-MM-DD HH:MM:SS.nnnnnnnnn`` (line k: frame k). ``*_extract``
drives hold the unrectified frames, which no ``P_rect`` projects.
"""

from __future__ import annotations

import calendar
import dataclasses
import os
import re
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, read_bytes
from gac_jax.data.kitti_calib import CAM_TO_CAM, Calibration
from gac_jax.data.kitti_oxts import camera_poses, read_oxts

_IMAGE_DIR = re.compile(r"image_0(\d)")
_TIMESTAMP = re.compile(r"(\d{4})-(\d{2})-(\d{2}) (\d{2}):(\d{2}):(\d{2})(?:\.(\d{1,9}))?")


@dataclasses.dataclass(frozen=True)
class RawDrive:
    """One camera of a raw drive folder ``DATE/DATE_drive_NNNN_sync`` (paths of the layout)."""

    drive: Path
    camera: int

    @classmethod
    def locate(cls, folder: str | os.PathLike, camera: int = 2) -> RawDrive | None:
        """The raw drive of ``folder``: a camera's ``image_0N/data``, its ``image_0N``, or the
        drive folder itself (one with some ``image_0N/data``; then camera ``camera``); None
        for any other folder. The camera of a named ``image_0N`` folder is N whatever
        ``camera`` says.

        Raises:
          KittiFormatError: the drive is an ``*_extract`` one (unrectified frames).
        """
        folder = Path(folder).resolve()
        if folder.name == "data" and (m := _IMAGE_DIR.fullmatch(folder.parent.name)):
            found = cls(folder.parents[1], int(m.group(1)))
        elif (m := _IMAGE_DIR.fullmatch(folder.name)) and (folder / "data").is_dir():
            found = cls(folder.parent, int(m.group(1)))
        elif any((folder / f"image_0{n}" / "data").is_dir() for n in range(4)):
            found = cls(folder, camera)  # the camera's folder may be missing: named later
        else:
            return None
        if found.drive.name.endswith("_extract"):
            raise KittiFormatError(
                found.drive,
                "a KITTI raw *_extract drive holds unrectified frames, which no P_rect "
                "projects: use the drive's *_sync download",
            )
        return found

    @property
    def day(self) -> Path:
        """``DATE/``: the folder of the day's calibration files."""
        return self.drive.parent

    @property
    def calib(self) -> Path:
        return self.day / CAM_TO_CAM

    @property
    def images(self) -> Path:
        return self.drive / f"image_0{self.camera}" / "data"

    @property
    def timestamps(self) -> Path:
        return self.drive / f"image_0{self.camera}" / "timestamps.txt"

    @property
    def oxts_dir(self) -> Path:
        return self.drive / "oxts" / "data"

    def frame_times(self, frames: Sequence[int]) -> np.ndarray:
        """(N,) seconds of ``frames`` (frame numbers) since the first of them, from
        :attr:`timestamps` (:func:`frame_times`)."""
        return frame_times(read_timestamps(self.timestamps), frames, self.timestamps)

    def poses(self, stems: Sequence[str], calib: Calibration) -> np.ndarray:
        """(N, 3, 4) camera poses of the frames named ``stems`` from their OXTS packets
        ``oxts/data/<stem>.txt``, relative to the first (:func:`kitti_oxts.camera_poses`)."""
        packets = []
        for stem in stems:
            path = self.oxts_dir / f"{stem}.txt"
            if not path.is_file():
                raise KittiFormatError(path, f"OXTS packet of frame {stem} not found")
            oxts = read_oxts(path)
            if len(oxts) != 1:
                raise KittiFormatError(path, f"{len(oxts)} OXTS packets; a raw drive has one")
            packets.append(oxts[0])
        return camera_poses(np.array(packets), calib)


def parse_timestamps(text: str, path: str | os.PathLike = "<timestamps>") -> np.ndarray:
    """(N,) int64 nanoseconds since the epoch of the ``YYYY-MM-DD HH:MM:SS.nnnnnnnnn`` lines
    of a ``timestamps.txt`` (read as UTC: only differences matter), line k frame k."""
    lines = text.rstrip().splitlines()
    out = np.zeros(len(lines), np.int64)
    for k, raw in enumerate(lines):
        m = _TIMESTAMP.fullmatch(raw.strip())
        if m is None:
            raise KittiFormatError(
                path, f"expected 'YYYY-MM-DD HH:MM:SS.nnnnnnnnn', got {raw[:40]!r}", k + 1
            )
        year, month, day, hour, minute, second = (int(g) for g in m.groups()[:6])
        if not (1 <= month <= 12 and 1 <= day <= 31 and hour < 24 and minute < 60 and second < 61):
            raise KittiFormatError(path, f"not a date and time: {raw.strip()!r}", k + 1)
        whole = calendar.timegm((year, month, day, hour, minute, second, 0, 0, 0))
        out[k] = whole * 10**9 + int((m.group(7) or "").ljust(9, "0"))
    if not len(out):
        raise KittiFormatError(path, "no timestamp in this file")
    return out


def read_timestamps(path: str | os.PathLike) -> np.ndarray:
    return parse_timestamps(read_bytes(path, "timestamps file").decode("utf-8", "replace"), path)


def frame_times(
    nanoseconds: np.ndarray, frames: Sequence[int], path: str | os.PathLike = "<timestamps>"
) -> np.ndarray:
    """(N,) float64 seconds since the first of ``frames`` (frame k: line k of the file),
    checked to increase.

    Raises:
      KittiFormatError: a frame without a line, or a time not after the previous frame's.
    """
    frames = list(frames)
    if frames and max(frames) >= len(nanoseconds):
        raise KittiFormatError(
            path, f"{len(nanoseconds)} timestamps for frames up to {max(frames)} (one per line)"
        )
    ns = nanoseconds[frames]
    for k in range(1, len(frames)):
        if ns[k] <= ns[k - 1]:
            raise KittiFormatError(
                path,
                f"frame {frames[k]}'s time is not after frame {frames[k - 1]}'s",
                frames[k] + 1,
            )
    return (ns - ns[:1]).astype(np.float64) / 1e9
