"""File helpers shared by every reader and writer: clear errors, atomic writes, PNG I/O."""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from gac_jax.data.io_errors import naming


class KittiFormatError(ValueError):
    """A KITTI-format file is missing or malformed. The message names the file (and line)."""

    def __init__(self, path: str | os.PathLike, problem: str, line: int | None = None):
        where = f"{os.fspath(path)}:{line}" if line is not None else os.fspath(path)
        super().__init__(f"{where}: {problem}")
        self.path = os.fspath(path)
        self.line = line
        self.problem = problem

    def __reduce__(self):
        # Picklable with its own arguments, so it crosses loader worker processes intact.
        return (type(self), (self.path, self.problem, self.line))


def _file_mode() -> int:
    umask = os.umask(0)  # (read once, at import: os.umask has no read-only form)
    os.umask(umask)
    return 0o666 & ~umask


FILE_MODE = _file_mode()  # the mode a plain open(path, "w") gives under this umask


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w") -> Iterator:
    """Opens a temporary file beside ``path`` and renames it over ``path`` on success.

    A reader never sees a half-written file, and an interrupted write leaves
    the previous version (if any) intact. A failed write (a full disk) raises an
    ``OSError`` that names ``path``.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as e:  # named for the user: the file, not the hidden temporary one
        raise OSError(e.errno, e.strerror, os.fspath(path)) from None
    try:
        with naming(path), os.fdopen(fd, mode) as f:
            os.fchmod(f.fileno(), FILE_MODE)  # mkstemp makes 0600; give what open() would
            yield f
        try:
            os.replace(tmp, path)
        except OSError as e:
            raise OSError(e.errno, e.strerror, os.fspath(path)) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_write(path, "wb") as f:
        f.write(data)


def read_bytes(path: str | os.PathLike, what: str = "file") -> bytes:
    try:
        return Path(path).read_bytes()
    except FileNotFoundError:
        raise KittiFormatError(path, f"{what} not found") from None
    except OSError as e:
        raise KittiFormatError(path, f"cannot read {what}: {e.strerror}") from None


def decode_image(data: bytes, path: str | os.PathLike = "<bytes>") -> np.ndarray:
    """Decodes PNG/JPEG bytes to an (H, W, 3) uint8 RGB array."""
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR_RGB)  # no BGR pass
    if img is None:
        raise KittiFormatError(path, "not a readable image (corrupt or unsupported file)")
    return img


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Reads an image file as (H, W, 3) uint8 RGB."""
    return decode_image(read_bytes(path, "image"), path)


def encode_png(
    image: np.ndarray, path: str | os.PathLike = "<array>", compression: int = 1
) -> bytes:
    """Encodes an (H, W, 3) uint8 RGB or (H, W) uint8/uint16 array as PNG bytes."""
    arr = np.asarray(image)
    if arr.ndim == 3:
        arr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", arr, [cv2.IMWRITE_PNG_COMPRESSION, compression])
    if not ok:
        raise KittiFormatError(path, f"cannot encode array of shape {arr.shape} as PNG")
    return buf.tobytes()


def write_png(path: str | os.PathLike, image: np.ndarray, compression: int = 1) -> None:
    """Atomically writes an RGB uint8 or a single-channel uint8/uint16 PNG."""
    write_bytes_atomic(path, encode_png(image, path, compression))


def decode_depth_png(data: bytes, path: str | os.PathLike = "<bytes>") -> np.ndarray:
    """Decodes a KITTI-depth 16-bit PNG to metres (float32, 0 = invalid)."""
    arr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise KittiFormatError(path, "not a readable PNG (corrupt or unsupported file)")
    if arr.dtype != np.uint16 or arr.ndim != 2:
        raise KittiFormatError(
            path, f"depth PNG must be single-channel 16-bit, got {arr.dtype} with shape {arr.shape}"
        )
    return arr.astype(np.float32) / 256.0


def read_depth_png(path: str | os.PathLike) -> np.ndarray:
    """Reads a KITTI-depth PNG: metres = value / 256, 0 = invalid. Returns (H, W) float32."""
    return decode_depth_png(read_bytes(path, "depth PNG"), path)


def depth_to_uint16(depth: np.ndarray) -> np.ndarray:
    """Metres -> KITTI-depth uint16 (round(depth * 256), 0 = invalid, saturates at 256 m)."""
    d = np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    return np.clip(np.round(d * 256.0), 0, 65535).astype(np.uint16)


def write_depth_png(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Atomically writes metres as a KITTI-depth 16-bit PNG."""
    write_png(path, depth_to_uint16(depth))
