"""Ground-aware convolution (GAC, paper Sec. "Ground-Aware Convolution Module"), NHWC.

Each feature pixel, treated as the centre of an object resting on the ground, looks *down*
to where that object would touch the road and gathers features there together with a
ground-plane depth prior. Pure helpers (all in feature-map pixel units):

* :func:`feature_projection` - ``P`` of the input image -> ``P`` of a stride-``s`` feature map.
* :func:`disparity_prior` - per-row virtual-stereo disparity of the ground plane.
* :func:`base_offset` - per-row geometric offset (rows) from an object centre to its
  ground contact point.
* :func:`bilinear_gather` - bilinear interpolation of a feature map at fractional (row,
  column) points; :func:`vertical_gather` - along the height axis only.

:func:`disparity_prior` and :func:`base_offset` are the paper's formulas, i.e. a level camera
``EL`` above the road. The module itself takes the frame's ground plane (``(B, 4)``, default
the level plane of ``camera_height``) and uses their general-plane forms, per pixel
(:mod:`gac_jax.models.ground_plane`), which equal these for a level plane.

Coordinates: feature row ``v`` (0 at the top, down positive) of a feature map whose
projection is ``P_f`` = ``P`` with rows 0 and 1 divided by the stride (what the reference
does; it treats feature pixel ``v`` as input pixel ``stride * v``). ``fy = P_f[1,1]``,
``cy = P_f[1,2]``, ``Ty = P_f[1,3]``. ``P`` is per image, (B,3,4), in pixels of the network
input: pass the calibration *after* crop/resize/flip.

Sampling convention (equal to the reference's ``grid_sample(..., align_corners=True,
padding_mode='border')`` with unchanged x): the reference adds ``base_rows / (H/2)`` and the
learned ``d`` to the normalised row coordinate, and normalised units are ``(H-1)/2`` rows, so
pixel ``(v, u)`` samples row::

    v + offset_rows,   offset_rows = (base_rows(v) / (H/2) + d[v, u]) * (H - 1) / 2

clamped to ``[0, H-1]``; i.e. the geometric offset is applied scaled by ``(H-1)/H`` and the
learned residual ``d`` (``|d| < 0.1``, normalised) spans at most ``0.05 (H-1)`` rows. The
column ``u + base_cols(v, u) * (W-1)/W`` (clamped to ``[0, W-1]``) follows the bottom point
sideways for a tilted plane (same scaling; no learned part); it is exactly ``u`` for a level
plane, where the sampling is therefore the reference's.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
from flax import linen as nn

from gac_jax.geometry import DEFAULT_CAMERA_HEIGHT, level_plane
from gac_jax.models.ground_plane import ground_maps
from gac_jax.models.initializers import torch_conv_bias_init, torch_conv_kernel_init

OFFSET_FORMULAS = ("paper", "reference", "reference_v1")
DEFAULT_BASELINE = 0.54  # m, virtual stereo baseline (KITTI-like)
DEFAULT_OBJECT_HEIGHT = 1.535  # m, mean object (car) height ("h_mean")


def _float_array(x) -> jax.Array:
    x = jnp.asarray(x)
    return x.astype(jnp.result_type(x.dtype, jnp.float32))


def frame_planes(plane: jax.Array | None, batch: int, camera_height: float, dtype) -> jax.Array:
    """(B, 4) ground planes: ``plane`` as given, or the level plane ``(0, -1, 0, camera_height)``.

    Args:
      plane: (B, 4) ``(a, b, c, d)`` with a unit upward normal (``b < 0``) in the rectified
        camera frame (:mod:`gac_jax.models.ground_plane`), or None.
    """
    if plane is None:
        return jnp.broadcast_to(jnp.asarray(level_plane(camera_height), dtype), (batch, 4))
    if plane.shape != (batch, 4):
        raise ValueError(f"plane must have shape (B,4) = {(batch, 4)}, got {plane.shape}")
    return jnp.asarray(plane, dtype)


def feature_projection(P: jax.Array, stride: float) -> jax.Array:
    """Projection of a stride-``stride`` feature map: rows 0 and 1 of ``P`` divided by stride.

    Args:
      P: (..., 3, 4) projection matrices in input-image pixels.
    Returns:
      (..., 3, 4) projection in feature-map pixels.
    """
    P = _float_array(P)
    if P.shape[-2:] != (3, 4):
        raise ValueError(f"P must have shape (..., 3, 4), got {P.shape}")
    scale = jnp.asarray([1.0 / stride, 1.0 / stride, 1.0], P.dtype)
    return P * scale[:, None]


def disparity_prior(
    height: int,
    P: jax.Array,
    stride: float,
    baseline: float = DEFAULT_BASELINE,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
) -> jax.Array:
    """Virtual disparity (feature pixels) of the ground plane at every feature row.

    ``disp(v) = ReLU(fy * B * (v - cy) / (|fy * EL + Ty| + 1e-10))`` with ``fy, cy, Ty`` of
    :func:`feature_projection` ``(P, stride)``: the disparity a stereo pair of baseline ``B``
    would see for a ground point (``y = EL`` below the camera) imaged at row ``v``; 0 at and
    above the horizon.

    Args:
      height: number of feature rows H.
      P: (..., 3, 4) projection of the network input (input-image pixels).
      stride: feature stride w.r.t. the input (16 for the detector).
    Returns:
      (..., H) disparity per row (shared by all columns).
    """
    Pf = feature_projection(P, stride)
    fy, cy, ty = Pf[..., 1, 1], Pf[..., 1, 2], Pf[..., 1, 3]
    v = jnp.arange(height, dtype=Pf.dtype)
    num = fy[..., None] * baseline * (v - cy[..., None])
    den = jnp.abs(fy * camera_height + ty)[..., None] + 1e-10
    return jax.nn.relu(num / den)


def base_offset(
    height: int,
    P: jax.Array,
    stride: float,
    object_height: float = DEFAULT_OBJECT_HEIGHT,
    camera_height: float = DEFAULT_CAMERA_HEIGHT,
    offset_formula: str = "paper",
) -> jax.Array:
    """Rows from an object centre at feature row ``v`` down to its ground contact point.

    An object of height ``h`` standing on the ground (camera ``EL`` above it) has its centre
    ``EL - h/2`` and its bottom ``EL`` below the camera, so at depth ``z`` the two project
    ``fy * (h/2) / z`` rows apart, with ``z = fy * (EL - h/2) / (v - cy)``:

    * ``'paper'``: ``delta_0 = h / (2 EL - h) * (v - cy)`` (the paper's formula);
    * ``'reference'``: ``h (v - cy) / (2 (EL - h/2))``, the reference code after its fix
      (issue #4) - algebraically identical to ``'paper'`` (≈ 0.870 (v - cy));
    * ``'reference_v1'``: ``h (v - cy) / 2 * (EL - h/2)``, the missing-parentheses version of
      release 1.0 (≈ 0.677 (v - cy)), which the released weights were most likely trained with.

    A ReLU (as in the reference) zeroes the offset above the horizon.

    Args:
      height: number of feature rows H.
      P: (..., 3, 4) projection of the network input (input-image pixels).
      stride: feature stride.
    Returns:
      (..., H) offset in feature rows (non-negative; down is positive).
    """
    if offset_formula not in OFFSET_FORMULAS:
        raise ValueError(f"offset_formula must be one of {OFFSET_FORMULAS}, got {offset_formula!r}")
    Pf = feature_projection(P, stride)
    cy = Pf[..., 1, 2]
    v = jnp.arange(height, dtype=Pf.dtype)
    dv = v - cy[..., None]
    h, el = object_height, camera_height
    if offset_formula == "paper":
        offset = h / (2.0 * el - h) * dv
    elif offset_formula == "reference":
        offset = h * dv / (2.0 * (el - h / 2.0))
    else:  # reference_v1: operator precedence as released
        offset = h * dv / 2.0 * (el - h / 2.0)
    return jax.nn.relu(offset)


def vertical_gather(features: jax.Array, rows: jax.Array) -> jax.Array:
    """Linearly interpolates ``features`` along the height axis at fractional ``rows``.

    ``out[b, v, u, c] = (1 - w) * features[b, r0, u, c] + w * features[b, r0 + 1, u, c]`` with
    ``r = clip(rows[b, v, u], 0, H - 1)``, ``r0 = min(floor(r), H - 2)``, ``w = r - r0``:
    border padding, like ``grid_sample(padding_mode='border', align_corners=True)`` when the
    columns are unchanged. Differentiable w.r.t. ``features`` and, through ``w``, w.r.t.
    ``rows`` (gradient ``features[r0 + 1] - features[r0]`` inside ``[0, H-1]``, 0 outside).

    Args:
      features: (B, H, W, C).
      rows: (B, H, W) float row coordinates (any range; clamped).
    Returns:
      (B, H, W, C) in the dtype of ``features``.
    """
    if features.ndim != 4 or rows.shape != features.shape[:3]:
        raise ValueError(
            f"expected features (B,H,W,C) and rows (B,H,W), got {features.shape} and {rows.shape}"
        )
    H = features.shape[1]
    rows = jnp.clip(rows, 0.0, H - 1.0)
    r0 = jnp.clip(jnp.floor(rows), 0.0, max(H - 2, 0))
    w = (rows - r0)[..., None].astype(features.dtype)
    i0 = r0.astype(jnp.int32)[..., None]
    i1 = jnp.minimum(i0 + 1, H - 1)
    f0 = jnp.take_along_axis(features, i0, axis=1)
    f1 = jnp.take_along_axis(features, i1, axis=1)
    return (1 - w) * f0 + w * f1


def bilinear_gather(features: jax.Array, rows: jax.Array, cols: jax.Array) -> jax.Array:
    """Bilinearly interpolates ``features`` at fractional ``(rows, cols)`` (border clamping).

    Each axis as :func:`vertical_gather`: ``r = clip(rows, 0, H-1)``, ``r0 = min(floor(r),
    H-2)``, ``wr = r - r0`` (likewise ``c0, wc`` on ``[0, W-1]``); rows are interpolated first
    in each of the columns ``c0, c0 + 1``, then the columns: at integer ``cols = u`` this is
    exactly :func:`vertical_gather` (``wc`` is 0, or 1 at the last column).

    Args:
      features: (B, H, W, C); rows, cols: (B, H, W) float coordinates (any range; clamped).
    Returns:
      (B, H, W, C) in the dtype of ``features``.
    """
    if features.ndim != 4 or rows.shape != features.shape[:3] or cols.shape != rows.shape:
        raise ValueError(
            f"expected features (B,H,W,C) and rows, cols (B,H,W), got {features.shape}, "
            f"{rows.shape} and {cols.shape}"
        )
    B, H, W, C = features.shape

    def taps(x, n):
        x = jnp.clip(x, 0.0, n - 1.0)
        i0 = jnp.clip(jnp.floor(x), 0.0, max(n - 2, 0))
        w = (x - i0)[..., None].astype(features.dtype)
        i0 = i0.astype(jnp.int32)
        return i0, jnp.minimum(i0 + 1, n - 1), w

    r0, r1, wr = taps(rows, H)
    c0, c1, wc = taps(cols, W)
    flat = features.reshape(B, H * W, C)

    def at(r, c):
        index = (r * W + c).reshape(B, H * W, 1)
        return jnp.take_along_axis(flat, index, axis=1).reshape(B, H, W, C)

    left = (1 - wr) * at(r0, c0) + wr * at(r1, c0)
    right = (1 - wr) * at(r0, c1) + wr * at(r1, c1)
    return (1 - wc) * left + wc * right


class GroundAwareConv(nn.Module):
    """The GAC module (reference ``LookGround``): C channels in, C channels out.

    Steps, for features ``x`` (B,H,W,C), the input-image projection ``P`` (B,3,4) and the
    ground ``plane`` (B,4) (None: the level plane of ``camera_height``, the paper's case):

    1. ``d0 = tanh(offset_conv(x))`` (conv 3x3 C->1), gradient-scaled as
       ``offset_grad_scale * d0 + (1 - offset_grad_scale) * stop_gradient(d0)`` (the forward
       value is unchanged, its gradient is scaled by 0.05), then ``d = offset_scale * d0``
       (normalised units, see the module docstring).
    2. ``G = [disparity ‖ x]`` (C+1 channels; the prior is channel 0), the plane's
       :func:`~gac_jax.models.ground_plane.ground_disparity` at each pixel
       (:func:`disparity_prior` for a level plane).
    3. ``S = bilinear_gather(G, v + offset_rows, u + offset_cols)`` with
       ``offset_rows = (base_rows / (H/2) + d) * (H-1)/2`` and
       ``offset_cols = base_cols / (W/2) * (W-1)/2``, ``(base_rows, base_cols)`` the plane's
       :func:`~gac_jax.models.ground_plane.ground_offset` (``(base_offset, 0)`` when level:
       then this is ``vertical_gather(G, v + offset_rows)``, the reference).
    4. ``out = ReLU(x + alpha * extract(S))``, ``extract`` = conv 1x1 (C+1)->C, ``alpha`` a
       learned scalar initialised to 0, so the module is the identity at init for ``x >= 0``.

    Returns ``{'features': (B,H,W,C), 'offset_rows': (B,H,W) rows from each pixel to its
    sample point (before clamping; the paper's Fig. 7 green points are at row
    ``v + offset_rows``), 'sample_rows': (B,H,W) clamped rows actually sampled,
    'offset_cols' / 'sample_cols': the same for columns (0 / ``u`` for a level plane)}``. Offsets
    and rows are in ``promote_types(dtype, float32)``: float32 for float32/bfloat16 modules,
    float64 for float64 ones (with ``jax_enable_x64``).
    """

    stride: float = 16
    baseline: float = DEFAULT_BASELINE
    camera_height: float = DEFAULT_CAMERA_HEIGHT
    object_height: float = DEFAULT_OBJECT_HEIGHT
    offset_formula: str = "paper"
    offset_scale: float = 0.1
    offset_grad_scale: float = 0.05
    dtype: Any = jnp.float32
    param_dtype: Any = jnp.float32

    @nn.compact
    def __call__(
        self, x: jax.Array, P: jax.Array, plane: jax.Array | None = None
    ) -> dict[str, jax.Array]:
        if x.ndim != 4:
            raise ValueError(f"expected NHWC features (B,H,W,C), got shape {x.shape}")
        B, H, W, C = x.shape
        if P.shape != (B, 3, 4):
            raise ValueError(f"P must have shape (B,3,4) = {(B, 3, 4)}, got {P.shape}")
        x = x.astype(self.dtype)
        # Geometry (offsets, sampling rows, the disparity prior) in the module's dtype, but
        # never below float32 (a bfloat16 row index near 17 has a 0.125-row step): float64
        # runs stay float64 end to end.
        geo = jnp.promote_types(self.dtype, jnp.float32)

        d0 = nn.Conv(
            1,
            (3, 3),
            padding=((1, 1), (1, 1)),
            kernel_init=torch_conv_kernel_init,
            bias_init=torch_conv_bias_init(9 * C),
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="offset_conv",
        )(x)
        d0 = jnp.tanh(d0[..., 0].astype(geo))
        g = self.offset_grad_scale
        d0 = g * d0 + (1.0 - g) * jax.lax.stop_gradient(d0)
        d = self.offset_scale * d0  # (B,H,W), grid_sample-normalised units

        if self.offset_formula not in OFFSET_FORMULAS:
            formula = self.offset_formula
            raise ValueError(f"offset_formula must be one of {OFFSET_FORMULAS}, got {formula!r}")
        Pf = feature_projection(jnp.asarray(P, geo), self.stride)
        base_rows, base_cols, disp = ground_maps(
            Pf,
            frame_planes(plane, B, self.camera_height, geo),
            (H, W),
            self.object_height,
            self.baseline,
            self.offset_formula,
        )  # (B,H,W) each
        offset_rows = (base_rows / (H / 2.0) + d) * ((H - 1) / 2.0)
        rows = jnp.arange(H, dtype=geo)[None, :, None] + offset_rows
        offset_cols = base_cols / (W / 2.0) * ((W - 1) / 2.0)
        cols = jnp.arange(W, dtype=geo)[None, None, :] + offset_cols

        disp_map = disp[..., None].astype(x.dtype)
        sampled = bilinear_gather(jnp.concatenate([disp_map, x], axis=-1), rows, cols)
        extracted = nn.Conv(
            C,
            (1, 1),
            kernel_init=torch_conv_kernel_init,
            bias_init=torch_conv_bias_init(C + 1),
            dtype=self.dtype,
            param_dtype=self.param_dtype,
            name="extract",
        )(sampled)
        alpha = self.param("alpha", nn.initializers.zeros, (1,), self.param_dtype)
        out = nn.relu(x + alpha.astype(self.dtype) * extracted)
        return {
            "features": out,
            "offset_rows": offset_rows,
            "sample_rows": jnp.clip(rows, 0.0, H - 1.0),
            "offset_cols": offset_cols,
            "sample_cols": jnp.clip(cols, 0.0, W - 1.0),
        }
