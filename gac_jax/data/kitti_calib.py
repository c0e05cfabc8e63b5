"""KITTI calibration files, in every format KITTI ships them, read by one reader.

Formats (one line per key, ``KEY: numbers`` or ``KEY numbers``; unknown keys are skipped):

* object benchmark ``calib/NNNNNN.txt``: ``P0:`` .. ``P3:``, ``R0_rect:``, ``Tr_velo_to_cam:``,
  ``Tr_imu_to_velo:``;
* tracking benchmark ``calib/SSSS.txt``: ``P0:`` .. ``P3:``, then ``R_rect``, ``Tr_velo_cam``,
  ``Tr_imu_velo`` (KITTI writes these three without a colon; both are read);
* raw data, one calibration per recording day in ``DATE/``:
  ``calib_cam_to_cam.txt`` (``P_rect_0N`` -> ``PN``, ``R_rect_00`` -> ``R0_rect``,
  ``S_rect_0N`` -> the rectified image sizes; ``calib_time``, ``corner_dist`` and the
  unrectified ``S_0N``, ``K_0N``, ``D_0N``, ``R_0N``, ``T_0N``, ``R_rect_0{1,2,3}`` are not
  used), ``calib_velo_to_cam.txt`` (``R``, ``T`` -> ``Tr_velo_to_cam``) and
  ``calib_imu_to_velo.txt`` (``R``, ``T`` -> ``Tr_imu_to_velo``).

Every format becomes one :class:`Calibration` with the object format's names; it keeps which
format and file it came from, so a missing key is reported under the file's own name
(``calibration has no P_rect_02``, ``... no Tr_imu_velo``). Frames: ``PN`` (3, 4) projects the
rectified camera-0 frame (x right, y down, z forward, metres) to camera N's pixels (u right,
v down); ``R0_rect`` (3, 3) rotates camera 0 into its rectified frame; ``Tr_velo_to_cam``
(3, 4) maps velodyne points (x forward, y left, z up) to camera 0 (unrectified);
``Tr_imu_to_velo`` (3, 4) maps IMU/GPS points (x forward, y left, z up) to the velodyne.
"""

from __future__ import annotations

import dataclasses
import os
import re
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from gac_jax.data.files import KittiFormatError, atomic_write, read_bytes

SHAPES = {
    "P0": (3, 4),
    "P1": (3, 4),
    "P2": (3, 4),
    "P3": (3, 4),
    "R0_rect": (3, 3),
    "Tr_velo_to_cam": (3, 4),
    "Tr_imu_to_velo": (3, 4),
}
# The key each format writes for each of SHAPES' keys.
FILE_KEYS = {
    "object": {k: k for k in SHAPES},
    "tracking": {
        **{f"P{n}": f"P{n}" for n in range(4)},
        "R0_rect": "R_rect",
        "Tr_velo_to_cam": "Tr_velo_cam",
        "Tr_imu_to_velo": "Tr_imu_velo",
    },
    "raw": {**{f"P{n}": f"P_rect_0{n}" for n in range(4)}, "R0_rect": "R_rect_00"},
}
CAM_TO_CAM = "calib_cam_to_cam.txt"
# The raw day's rigid-transform files (R, T) beside calib_cam_to_cam.txt, and their key.
RIGID_FILES = {"calib_velo_to_cam.txt": "Tr_velo_to_cam", "calib_imu_to_velo.txt": "Tr_imu_to_velo"}
_ALIASES: dict[str, tuple[str, str]] = {}  # file key -> (first format naming it so, key)
for _fmt, _keys in FILE_KEYS.items():
    for _key, _file_key in _keys.items():
        _ALIASES.setdefault(_file_key, (_fmt, _key))
_SIZE_KEY = re.compile(r"S_rect_0(\d)")
_LINE = re.compile(r"([A-Za-z_]\w*)\s*(:?)(.*)")
_RIGID_ONLY = f"holds only R and T of a rigid transform; give the day's {CAM_TO_CAM}"
_PURPOSE = {"P2": "the left colour camera projection", "P3": "the right colour camera projection"}


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Calibration of one KITTI frame, sequence or recording day (float64). Only ``P2`` is
    mandatory (unless read for another camera: :func:`parse_calib`).

    Attributes:
      P0 .. P3: (3, 4) projections of the rectified cameras (module docstring).
      R0_rect: (3, 3) rectifying rotation of camera 0.
      Tr_velo_to_cam: (3, 4) velodyne -> camera 0.
      Tr_imu_to_velo: (3, 4) IMU -> velodyne.
      image_sizes: camera -> ``(height, width)`` of its rectified images (raw ``S_rect_0N``).
      kind: the file format: ``"object"``, ``"tracking"`` or ``"raw"``.
      path: the file read (None: built in code).
    """

    P2: np.ndarray | None
    P0: np.ndarray | None = None
    P1: np.ndarray | None = None
    P3: np.ndarray | None = None
    R0_rect: np.ndarray | None = None
    Tr_velo_to_cam: np.ndarray | None = None
    Tr_imu_to_velo: np.ndarray | None = None
    image_sizes: Mapping[int, tuple[int, int]] = dataclasses.field(default_factory=dict)
    kind: str = "object"
    path: str | None = None

    def file_key(self, key: str) -> str:
        """The name this calibration's format gives ``key`` (``P2`` -> raw ``P_rect_02``)."""
        return FILE_KEYS[self.kind].get(key, key)

    def require(self, key: str, why: str) -> np.ndarray:
        """``key`` (one of :data:`SHAPES`), or a :class:`KittiFormatError` naming the file and
        the key as that file names it; ``why`` (e.g. "needed for the OXTS poses") ends it."""
        value = getattr(self, key)
        if value is not None:
            return value
        if self.kind == "raw" and key in RIGID_FILES.values():
            name = next(n for n, k in RIGID_FILES.items() if k == key)
            where = (Path(self.path).parent if self.path else Path(".")) / name
            found = "not read with the calibration" if where.is_file() else "not found"
            raise KittiFormatError(where, f"{found}; its R and T are {why}")
        where = self.path or "calibration"
        raise KittiFormatError(where, f"calibration has no {self.file_key(key)} ({why})")

    def projection(self, camera: int) -> np.ndarray:
        """(3, 4) ``P<camera>`` (camera 0..3), or the error naming the missing key."""
        return self.require(f"P{camera}", _PURPOSE.get(f"P{camera}", f"camera {camera}"))


def _numbers(fields: list[str], key: str, n: int, path, lineno: int) -> np.ndarray:
    if len(fields) != n:
        raise KittiFormatError(path, f"{key} needs {n} numbers, found {len(fields)}", lineno)
    values = []
    for f in fields:
        try:
            values.append(float(f))
        except ValueError:
            raise KittiFormatError(path, f"{key}: non-numeric value {f!r}", lineno) from None
    if not np.all(np.isfinite(values)):
        raise KittiFormatError(path, f"{key}: non-finite value", lineno)
    return np.array(values, dtype=np.float64)


def _entries(text: str, path, known) -> dict[str, tuple[list[str], int]]:
    """``KEY: v1 v2 ...`` / ``KEY v1 v2 ...`` lines -> key -> (fields, line number). A line
    without a colon must start with a key in ``known`` (the tracking format's way);
    a key in ``known`` given twice is an error."""
    out: dict[str, tuple[list[str], int]] = {}
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line:
            continue
        m = _LINE.fullmatch(line)
        if m is None or (not m.group(2) and not known(m.group(1))):
            raise KittiFormatError(path, f"expected 'KEY: v1 v2 ...', got {line[:40]!r}", lineno)
        key = m.group(1)
        if key in out and known(key):
            raise KittiFormatError(path, f"{key} given twice (lines {out[key][1]} and {lineno})")
        out[key] = (m.group(3).split(), lineno)
    return out


def parse_calib(
    text: str, path: str | os.PathLike = "<calib>", camera: int | None = 2
) -> Calibration:
    """Parses the text of one calibration file of any format but the rigid-transform files
    (object, tracking, raw ``calib_cam_to_cam.txt``; module docstring). ``camera``: the
    projection that must be there (2: ``P2``; None: none, :meth:`Calibration.projection`
    names a missing one when asked).

    Raises:
      KittiFormatError: a malformed line or value (naming the line and key), a key given
        twice (or under two formats' names), no ``P<camera>`` (raw: ``P_rect_0<camera>``),
        or a singular projection.
    """
    entries = _entries(text, path, lambda k: k in _ALIASES or bool(_SIZE_KEY.fullmatch(k)))
    values: dict[str, np.ndarray] = {}
    given: dict[str, str] = {}  # key -> the file's name for it
    sizes: dict[int, tuple[int, int]] = {}
    for file_key, (fields, lineno) in entries.items():
        if (m := _SIZE_KEY.fullmatch(file_key)) is not None:
            width, height = _numbers(fields, file_key, 2, path, lineno)
            if width <= 0 or height <= 0 or width != int(width) or height != int(height):
                raise KittiFormatError(
                    path, f"{file_key} must be two positive integers (W H)", lineno
                )
            sizes[int(m.group(1))] = (int(height), int(width))
        elif file_key in _ALIASES:  # else calib_time, K_0N, D_0N, ...: not used
            key = _ALIASES[file_key][1]
            if key in given:
                raise KittiFormatError(
                    path, f"{given[key]} and {file_key} are the same quantity", lineno
                )
            shape = SHAPES[key]
            values[key] = _numbers(fields, file_key, shape[0] * shape[1], path, lineno)
            values[key] = values[key].reshape(shape)
            given[key] = file_key
    formats = {_ALIASES[k][0] for k in given.values()} | ({"raw"} if sizes else set())
    kind = next((f for f in ("raw", "tracking") if f in formats), "object")
    for key in ("P0", "P1", "P2", "P3"):
        if key in values and abs(np.linalg.det(values[key][:, :3])) < 1e-12:
            line = entries[given[key]][1]
            raise KittiFormatError(path, f"{given[key]} is singular", line)
    calib = Calibration(
        **{"P2": None, **values}, image_sizes=sizes, kind=kind, path=os.fspath(path)
    )
    if camera is not None and f"P{camera}" not in values:
        if not values and {"R", "T"} <= set(entries):
            raise KittiFormatError(path, _RIGID_ONLY)
        calib.projection(camera)  # raises, naming the key
    return calib


def parse_rigid(text: str, path: str | os.PathLike = "<calib>") -> np.ndarray:
    """(3, 4) ``[R | T]`` of a raw ``calib_velo_to_cam.txt`` / ``calib_imu_to_velo.txt``
    (``R``: 9 numbers row-major, ``T``: 3; ``calib_time``, ``delta_f``, ``delta_c`` skipped)."""
    entries = _entries(text, path, lambda k: k in ("R", "T"))
    parts = []
    for key, n, what in (("R", 9, "rotation"), ("T", 3, "translation")):
        if key not in entries:
            raise KittiFormatError(path, f"calibration has no {key} (the {what})")
        fields, lineno = entries[key]
        parts.append(_numbers(fields, key, n, path, lineno))
    return np.concatenate([parts[0].reshape(3, 3), parts[1][:, None]], axis=1)


def _text(path) -> str:
    return read_bytes(path, "calibration file").decode("utf-8", "replace")


def read_calib(path: str | os.PathLike, camera: int | None = 2) -> Calibration:
    """Reads any KITTI calibration: an object or tracking file, a raw ``calib_cam_to_cam.txt``
    or a raw day's folder holding it. With a raw file, the day's ``calib_velo_to_cam.txt``
    and ``calib_imu_to_velo.txt`` beside it are read too where present (KITTI ships the day's
    calibration as these three files). ``camera``: as :func:`parse_calib`."""
    path = Path(path)
    if path.is_dir():
        if not (path / CAM_TO_CAM).is_file():
            raise KittiFormatError(
                path, f"no {CAM_TO_CAM} in this folder (a KITTI raw day's calibration)"
            )
        path = path / CAM_TO_CAM
    if path.name in RIGID_FILES:
        raise KittiFormatError(path, _RIGID_ONLY)
    calib = parse_calib(_text(path), path, camera)
    if calib.kind != "raw":
        return calib
    rigid = {}
    for name, key in RIGID_FILES.items():
        if (path.parent / name).is_file():
            rigid[key] = parse_rigid(_text(path.parent / name), path.parent / name)
    return dataclasses.replace(calib, **rigid)


def format_calib(calib: Calibration) -> str:
    """The object format's text of ``calib`` (whatever format it was read from)."""
    lines = []
    for key in SHAPES:
        arr = getattr(calib, key)
        if arr is not None:
            lines.append(f"{key}: " + " ".join(f"{v:.12e}" for v in np.ravel(arr)))
    return "\n".join(lines) + "\n"


def write_calib(path: str | os.PathLike, calib: Calibration) -> None:
    with atomic_write(path) as f:
        f.write(format_calib(calib))
