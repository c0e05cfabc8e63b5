"""Matching tracks to detections: costs, gates and the optimal assignment.

* :func:`measurement_covariance`: a monocular detection's position error, long along the
  viewing ray and growing with distance (:class:`~gac_jax.tracking.params.TrackerParams`).
* :func:`mahalanobis_costs`: squared Mahalanobis distances of detected centres to predicted
  ones; gating them at a chi-square quantile makes the gate grow with distance, as the
  depth error does.
* :func:`assign`: Hungarian assignment (``scipy.optimize.linear_sum_assignment``) of the
  pairs a gate allows.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from gac_jax.detection.nms import box_iou_matrix

__all__ = ["assign", "box_iou_matrix", "mahalanobis_costs", "measurement_covariance"]


def measurement_covariance(points: np.ndarray, params) -> np.ndarray:
    """(N, 3, 3) position covariance of detections at camera-frame ``points`` (N, 3):
    ``sd^2 u u^T + sl^2 (I - u u^T)``, ``u`` the unit ray, ``sd = depth_std + depth_std_per_m
    r`` along it and ``sl = lateral_std + lateral_std_per_m r`` across (``r`` the distance)."""
    r = np.linalg.norm(points, axis=1)
    u = points / np.maximum(r, 1e-6)[:, None]
    along = np.einsum("ni,nj->nij", u, u)
    sd = params.depth_std + params.depth_std_per_m * r
    sl = params.lateral_std + params.lateral_std_per_m * r
    return (sd**2)[:, None, None] * along + (sl**2)[:, None, None] * (np.eye(3) - along)


def mahalanobis_costs(predicted: np.ndarray, S: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """(T, N) squared distances ``(z_j - p_i)^T S_i^-1 (z_j - p_i)`` of measured positions
    ``measured`` (N, d) to predicted ones ``predicted`` (T, d) with innovation covariances
    ``S`` (T, d, d)."""
    diff = measured[None, :, :] - predicted[:, None, :]  # (T, N, d)
    S_inv = np.linalg.inv(S)
    return np.einsum("tni,tij,tnj->tn", diff, S_inv, diff)


def assign(cost: np.ndarray, allowed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(rows, cols)`` of least total ``cost`` (T, N) among the ``allowed`` (T, N)
    ones (each row and column at most once; rows or columns with no allowed pair stay out)."""
    if not allowed.any():
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    rows_in = np.flatnonzero(allowed.any(axis=1))
    cols_in = np.flatnonzero(allowed.any(axis=0))
    sub_allowed = allowed[rows_in][:, cols_in]
    sub = cost[rows_in][:, cols_in]
    big = 1.0 + 2.0 * np.abs(np.where(sub_allowed, sub, 0.0)).sum()  # worse than any allowed set
    rows, cols = linear_sum_assignment(np.where(sub_allowed, sub, big))
    keep = sub_allowed[rows, cols]
    return rows_in[rows[keep]], cols_in[cols[keep]]
