"""Checks of what a caller hands the inference API, and the one error they raise.

:class:`InputError` (a ``ValueError``) names the argument and the problem in one line:
``image: expected an RGB uint8 array (H, W, 3), got float32 (375, 1242, 3)``. Images are
RGB ``uint8`` ``(H, W, 3)`` of any size; ``P2`` is the ``(3, 4)`` projection of that image
(camera frame: x right, y down, z forward; image: u right, v down); ``plane`` is ``(a, b, c,
d)`` of the road ``a x + b y + c z + d = 0`` in that camera frame with a unit normal pointing
up (``b < 0``; ``| |(a, b, c)| - 1 | <=`` :data:`PLANE_NORM_TOLERANCE`), so ``d`` is the
camera's height above it, > 0 (:func:`gac_jax.geometry.normalize_plane` makes one from any
scale). ``P2`` must be invertible and fit its image (:func:`check_fits`: the check the stream
CLI applies to its calibration files too), and the image must keep at least one column when
resized to the network's input height.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from gac_jax.data.sources import new_sample

PLANE_NORM_TOLERANCE = 1e-3
MAX_CONDITION = 1e12  # of P2's left 3x3 block: beyond it, singular in float64
# the principal point must lie in the middle 40 % of each image axis: a camera's is within a few
# per cent of the centre; the calibration of half (or twice) the picture's size puts it at a
# quarter of the frame (KITTI's halved: u = 0.25 W, v = 0.23 H), of another camera near an edge
CENTRE_BAND = 0.4


class InputError(ValueError):
    """Bad input to the inference API: ``<argument>: <problem>`` (one line).

    Attributes:
      argument: the argument's name (``image``, ``P2``, ``plane``, ``workdir``, ...).
      problem: what is wrong with it.
    """

    def __init__(self, argument: str, problem: str):
        super().__init__(f"{argument}: {problem}")
        self.argument = argument
        self.problem = problem


def _described(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array of shape {value.shape}"
    return type(value).__name__


def check_image(image: Any, name: str = "image", min_rows: int = 1) -> np.ndarray:
    """``image`` as an RGB uint8 ``(H, W, 3)`` array with ``H >= min_rows`` rows.

    Raises:
      InputError: not a numpy array, another dtype, rank or channel count, an empty image,
        or fewer rows than ``min_rows`` (the model crops some top rows).
    """
    if not isinstance(image, np.ndarray):
        raise InputError(
            name, f"expected a numpy RGB uint8 array (H, W, 3), got {_described(image)}"
        )
    if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        raise InputError(name, f"expected an RGB uint8 array (H, W, 3), got {_described(image)}")
    h, w = image.shape[:2]
    if h < min_rows or w < 1:
        raise InputError(
            name, f"image is {h}x{w} (H x W); the model needs at least {min_rows} rows"
        )
    return image


def check_projection(P2: Any, name: str = "P2") -> np.ndarray:
    """``P2`` as a finite (3, 4) float64 projection with positive focal lengths.

    Raises:
      InputError: another shape, non-numeric or non-finite values, ``P2[0, 0]`` or
        ``P2[1, 1]`` (the focal lengths in pixels) not positive.
    """
    try:
        P = np.asarray(P2, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            name, f"expected a (3, 4) projection matrix, got {_described(P2)}"
        ) from None
    if P.shape != (3, 4):
        raise InputError(name, f"expected a (3, 4) projection matrix, got shape {P.shape}")
    if not np.all(np.isfinite(P)):
        raise InputError(name, "has non-finite values (NaN or inf)")
    if not (P[0, 0] > 0 and P[1, 1] > 0):
        raise InputError(
            name, f"focal lengths P2[0, 0] = {P[0, 0]:g} and P2[1, 1] = {P[1, 1]:g} must be > 0"
        )
    if not np.linalg.cond(P[:, :3]) < MAX_CONDITION:
        raise InputError(
            name,
            "is singular: its left 3x3 block cannot be inverted (a camera projection's third "
            "row is (0, 0, 1, t))",
        )
    return P


def check_fits(
    P2: np.ndarray,
    size: tuple[int, int],
    name: str = "P2",
    what: str = "image",
    centre_band: bool = False,
) -> None:
    """Raises :class:`InputError` if ``P2`` cannot be the projection of an image of
    ``size = (H, W)``: its principal point ``(P2[0, 2], P2[1, 2])`` must lie in the image.
    ``centre_band``: also in its middle :data:`CENTRE_BAND` along each axis, the stream CLI's
    check of a calibration file (a point far from the centre means the calibration of another
    image size: KITTI's 1242 x 375 one on a 640 x 480 camera puts it at u = 609 of 640, its
    halved one on the full frame at a quarter; the API does not ask it, a cropped image may
    have its point near an edge). ``what`` names the image in the message."""
    h, w = size
    cu, cv = float(P2[0, 2]), float(P2[1, 2])
    where = f"the {w}x{h} {what}"
    if not (0 <= cu <= w - 1 and 0 <= cv <= h - 1):
        raise InputError(
            name,
            f"does not fit {where}: its principal point ({cu:.1f}, {cv:.1f}) is outside "
            "the frame (a calibration of another image size?)",
        )
    lo, hi = (1 - CENTRE_BAND) / 2, (1 + CENTRE_BAND) / 2
    if centre_band and not (lo * w <= cu <= hi * w and lo * h <= cv <= hi * h):
        raise InputError(
            name,
            f"does not fit {where}: its principal point ({cu:.1f}, {cv:.1f}) is far from "
            f"the centre (expected within the middle {CENTRE_BAND:.0%} of each axis; a "
            "calibration of another image size?)",
        )


def check_resized(image: np.ndarray, rows: int, height: int, name: str = "image") -> None:
    """Raises :class:`InputError` when ``rows`` rows of ``image`` resized to the network's
    ``height`` rows (aspect kept) leave no column: an image far taller than wide."""
    h, w = image.shape[:2]
    width = int(round(w * height / rows))
    if width < 1:
        raise InputError(
            name,
            f"image is {h}x{w} (H x W): resized to the model's {height}-row input it would be "
            f"{width} pixels wide (far taller than wide; crop it to a camera's aspect)",
        )


def check_plane(plane: Any, name: str = "plane") -> np.ndarray | None:
    """``plane`` as a (4,) float64 ground plane, or None (the config's level camera).

    Raises:
      InputError: not 4 finite numbers, a normal whose length is not 1 (within
        :data:`PLANE_NORM_TOLERANCE`) or that does not point up (``b < 0``).
    """
    if plane is None:
        return None
    try:
        p = np.asarray(plane, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(
            name, f"expected 4 numbers (a, b, c, d), got {_described(plane)}"
        ) from None
    if p.shape != (4,):
        raise InputError(name, f"expected 4 numbers (a, b, c, d), got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise InputError(name, "has non-finite values (NaN or inf)")
    norm = float(np.linalg.norm(p[:3]))
    if abs(norm - 1.0) > PLANE_NORM_TOLERANCE:
        raise InputError(
            name,
            f"normal (a, b, c) has length {norm:.6g}, not 1 (tolerance {PLANE_NORM_TOLERANCE:g}); "
            "scale it with gac_jax.geometry.normalize_plane",
        )
    if not p[1] < 0:
        raise InputError(
            name, f"normal must point up (b < 0 in the camera frame, y down), got b = {p[1]:g}"
        )
    if not p[3] > 0:
        raise InputError(
            name,
            f"d = {p[3]:g}: the camera must be above the ground (d is its height in metres, "
            "> 0); the plane runs through or above it",
        )
    return p


def image_sample(
    image: Any,
    P2: Any,
    plane: Any = None,
    min_rows: int = 1,
    resize: tuple[int, int] | None = None,
) -> dict:
    """A checked (image, P2, plane) as a fresh sample of the data pipeline
    (:func:`gac_jax.data.sources.new_sample`: identity ``image_transform``), ready for a test
    transform; without ``plane`` the sample has none (the model's level camera).

    ``resize = (top, height)``: the transform resizes the rows below the first ``top`` to
    ``height`` (:func:`check_resized`). ``P2`` must fit the image (:func:`check_fits`)."""
    image = check_image(image, min_rows=min_rows)
    if resize is not None:
        check_resized(image, image.shape[0] - resize[0], resize[1])
    P = check_projection(P2)
    check_fits(P, image.shape[:2])
    p = check_plane(plane)
    extra = {} if p is None else {"plane": p}
    return new_sample("image", 2, image, P, **extra)


def check_batch(images: Any, P2s: Any, planes: Any) -> tuple[list, list, list]:
    """``(images, P2s, planes)`` of a batch call as lists of equal length (``planes`` None:
    one None per image).

    Raises:
      InputError: ``images`` is one array instead of a sequence, or the lengths differ.
    """
    if isinstance(images, np.ndarray) and images.ndim != 4:
        raise InputError("images", f"expected a sequence of images, got {_described(images)}")
    images = list(images)
    P2s = list(P2s) if not isinstance(P2s, np.ndarray) or P2s.ndim == 3 else [P2s]
    if len(P2s) != len(images):
        raise InputError("P2s", f"{len(P2s)} projection matrices for {len(images)} images")
    if planes is None:
        planes = [None] * len(images)
    planes = list(planes)
    if len(planes) != len(images):
        raise InputError("planes", f"{len(planes)} planes for {len(images)} images")
    return images, P2s, planes


def prepare_batch(prepare: Callable, images: Any, P2s: Any, planes: Any) -> list:
    """``[prepare(image, P2, plane), ...]`` over a batch call's arguments
    (:func:`check_batch`); an image's error names it: ``images[3]: ...``, ``P2s[0]: ...``."""
    images, P2s, planes = check_batch(images, P2s, planes)
    out = []
    for i, (image, P2, plane) in enumerate(zip(images, P2s, planes, strict=True)):
        try:
            out.append(prepare(image, P2, plane))
        except InputError as e:
            raise InputError(f"{e.argument}s[{i}]", e.problem) from None
    return out


def check_choice(value: Any, choices: Sequence[str], name: str) -> str:
    if value not in choices:
        raise InputError(name, f"must be one of {', '.join(choices)}, got {value!r}")
    return value


def check_positive_int(value: Any, name: str, allow_none: bool = False) -> int | None:
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 1:
        raise InputError(name, f"must be an integer >= 1, got {value!r}")
    return int(value)


def check_step(step: Any) -> int | None:
    if step is None:
        return None
    if isinstance(step, bool) or not isinstance(step, int | np.integer) or step < 0:
        raise InputError(
            "step", f"must be a checkpoint step (an integer >= 0) or None, got {step!r}"
        )
    return int(step)


def check_score_threshold(value: Any) -> float | None:
    if value is None:
        return None
    try:
        score = float(value)
    except (TypeError, ValueError):
        raise InputError("score_threshold", f"must be a number, got {value!r}") from None
    if not math.isfinite(score):
        raise InputError("score_threshold", f"must be finite, got {value!r}")
    return score
