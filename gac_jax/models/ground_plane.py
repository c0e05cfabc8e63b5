"""GAC's geometry for a general ground plane: sampling offset and disparity prior per pixel.

The road is the plane ``n . X + d = 0`` (``plane = (a, b, c, d)``, ``n = (a, b, c)``) in the
rectified reference camera frame (x right, y down, z forward, metres): ``n`` is a unit normal
pointing *up* (``b < 0``) and ``d > 0`` the camera's height above the road, so a point's height
above the road is ``n . X + d``. A level camera ``EL`` above the road is ``(0, -1, 0, EL)``
(:func:`gac_jax.geometry.level_plane`; the KITTI-format ``planes/`` files give it per frame).

Feature-map projection ``P_f = [M | p]`` (:func:`~gac_jax.models.ground_aware_conv.
feature_projection`), rows ``m0, m1, m2`` of ``M``; feature pixel ``(u, v)``; ``k = h / 2``
for the object height ``h``. Terms per frame (:func:`plane_terms`):

* ``w = M^-T n``, so ``n . r(u, v) = w0 u + w1 v + w2`` for the ray ``r = M^-1 [u, v, 1]``
  (``w_i = n . (m_{i+1} x m_{i+2}) / det M``; ``r_z = 1`` for KITTI-structured ``P``, so the
  ray parameter is the depth ``z``); ``down = -n . r`` > 0 where the ray descends to the road.
* ``g = M n``: the image-space direction of the plane normal.

**Offset** (:func:`ground_offset`, from the origin: the reference's offset ignores ``p``).
The object centre seen at ``(u, v)`` is ``X_c = z r`` with ``n . X_c + d = k``, so
``1 / z = down / (d - k)``; its bottom point on the road is ``X_b = X_c - k n``, imaged at
``v_b = (z v - k g1) / (z - k g2)``. Hence::

    offset = v_b - v = k (v g2 - g1) down / (d - k - k g2 down)

(ReLU'd, 0 above the horizon, as the reference), and likewise it lies
``k (u g2 - g0) down / (d - k - k g2 down)`` columns to the side. For ``(0, -1, 0, EL)`` and
``M`` of KITTI structure: ``g = (0, -fy, 0)``, ``down = (v - cy) / fy``, so
``offset = k (v - cy) / (EL - k) = h (v - cy) / (2 EL - h)``: the paper's formula ('paper' and
'reference'). 'reference_v1' (release 1.0's missing parentheses, ``h (v - cy) / 2 * (EL -
h/2)``) generalises as the true offset (both parts) times ``(d - k)^2``. The sideways part is
exactly 0 for a level plane (``g0 = 0``), so GAC there samples its own column as the
reference's ``grid_sample`` with unchanged x does; for a pitched or rolled camera it follows
the bottom point sideways too.

**Disparity prior** (:func:`ground_disparity`): the virtual stereo disparity ``fy B / z_g`` of
the road point seen at ``(u, v)``, on the ray from ``-M^-1 [Tx, Ty, 0]`` (the reference keeps
``P``'s ``Ty`` here and drops ``Tz``): ``1 / z_g = down / (d + n . q)`` with
``n . q = -(w0 Tx + w1 Ty)``::

    disparity = ReLU(fy B (fy down) / (|fy (d + n . q)| + 1e-10))

which for a level plane is the paper's ``fy B (v - cy) / (fy EL + Ty)``.

The functions only use ``+ - * /`` and the ``ops`` given (``relu``, ``abs``, ``maximum``), so
the same code builds the JAX computation (:data:`JNP_OPS`, arrays) and the exported ONNX graph
(:mod:`gac_jax.deploy.export.networks`, symbolic tensors): ``P[i][j]`` and ``plane[i]`` are
per-frame values broadcastable against the pixel grids ``u`` (columns) and ``v`` (rows).
"""

from __future__ import annotations

from types import SimpleNamespace

import jax
import jax.numpy as jnp

JNP_OPS = SimpleNamespace(relu=jax.nn.relu, abs=jnp.abs, maximum=jnp.maximum)
MIN_DEPTH_RATIO = 1e-6  # floor of the offset's denominator (bottom point behind the camera)


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def plane_terms(P, plane) -> dict:
    """Per-frame terms of a plane seen through a feature-map projection (module docstring).

    Args:
      P: 3x4 nested sequence ``P[i][j]`` of per-frame values (feature-map pixels).
      plane: 4 per-frame values ``(a, b, c, d)``, unit upward normal.
    Returns:
      ``{'w': (w0, w1, w2), 'g': (g0, g1, g2), 'd', 'nq', 'fy'}``.
    """
    m = [tuple(P[i][:3]) for i in range(3)]
    n, d = tuple(plane[:3]), plane[3]
    cof = (_cross(m[1], m[2]), _cross(m[2], m[0]), _cross(m[0], m[1]))
    det = _dot(m[0], cof[0])
    w = tuple(_dot(n, c) / det for c in cof)
    g = tuple(_dot(row, n) for row in m)
    nq = -(w[0] * P[0][3] + w[1] * P[1][3])
    return {"w": w, "g": g, "d": d, "nq": nq, "fy": P[1][1]}


def _down(terms, u, v):
    w = terms["w"]
    return -(w[0] * u + w[1] * v + w[2])


def ground_offset(terms, u, v, object_height: float, offset_formula: str, ops=JNP_OPS):
    """``(rows, cols)`` from the object centre at ``(u, v)`` to its road contact point.

    ``rows = ReLU(k (v g2 - g1) down / den)`` (>= 0, down the image) and
    ``cols = k (u g2 - g0) down / den`` with ``den = d - k - k g2 down`` (floored at
    ``MIN_DEPTH_RATIO``); both 0 above the horizon, ``cols`` 0 for a level plane. For
    ``'reference_v1'`` both are scaled by ``(d - k)^2``.
    """
    k = object_height / 2.0
    g, d = terms["g"], terms["d"]
    down = ops.relu(_down(terms, u, v))
    ratio = k * down / ops.maximum(d - k - k * g[2] * down, MIN_DEPTH_RATIO)
    rows = ops.relu((v * g[2] - g[1]) * ratio)
    cols = (u * g[2] - g[0]) * ratio
    if offset_formula == "reference_v1":
        scale = (d - k) * (d - k)
        rows, cols = rows * scale, cols * scale
    return rows, cols


def ground_disparity(terms, u, v, baseline: float, ops=JNP_OPS):
    """Virtual disparity (feature pixels) of the road point seen at ``(u, v)`` (>= 0)."""
    fy = terms["fy"]
    num = fy * baseline * (fy * _down(terms, u, v))
    return ops.relu(num / (ops.abs(fy * (terms["d"] + terms["nq"])) + 1e-10))


def _entries(Pf: jax.Array, plane: jax.Array):
    """(B,3,4) and (B,4) arrays -> nested per-frame (B,1,1) values for :func:`plane_terms`."""
    P = [[Pf[:, i, j][:, None, None] for j in range(4)] for i in range(3)]
    return P, [plane[:, i][:, None, None] for i in range(4)]


def ground_maps(
    Pf: jax.Array,
    plane: jax.Array,
    size: tuple[int, int],
    object_height: float,
    baseline: float,
    offset_formula: str,
) -> tuple[jax.Array, jax.Array, jax.Array]:
    """``(offset rows, offset cols, disparity)`` (:func:`ground_offset`,
    :func:`ground_disparity`) at every pixel of an (H, W) feature map.

    Args:
      Pf: (B, 3, 4) feature-map projection; plane: (B, 4) unit upward normal + height.
    Returns:
      three (B, H, W) arrays in the dtype of ``Pf``.
    """
    H, W = size
    terms = plane_terms(*_entries(Pf, jnp.asarray(plane, Pf.dtype)))
    u = jnp.arange(W, dtype=Pf.dtype)[None, None, :]
    v = jnp.arange(H, dtype=Pf.dtype)[None, :, None]
    rows, cols = ground_offset(terms, u, v, object_height, offset_formula)
    disparity = ground_disparity(terms, u, v, baseline)
    shape = (Pf.shape[0], H, W)
    return tuple(jnp.broadcast_to(x, shape) for x in (rows, cols, disparity))
