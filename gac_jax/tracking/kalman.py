"""Constant-velocity Kalman filters, many at once (pure numpy, float64).

State of one filter: ``x = (p, v)`` with ``p`` a position of ``d`` coordinates and ``v`` its
rate (units per second), ``x`` of shape ``(2 d,)``, covariance ``P`` ``(2 d, 2 d)``. The
measurement is the position alone (``H = [I 0]``). Every function takes ``T`` filters stacked
(``x`` (T, 2 d), ``P`` (T, 2 d, 2 d)) and returns new arrays (its inputs are not changed).

The motion model is the discrete white-noise acceleration one: over ``dt`` seconds each
coordinate takes a constant random acceleration of standard deviation ``accel_std``, so

    F = [[I, dt I], [0, I]],   Q = accel_std^2 [[dt^4/4 I, dt^3/2 I], [dt^3/2 I, dt^2 I]].
"""

from __future__ import annotations

import numpy as np


def transition(dt: float, dim: int) -> np.ndarray:
    """(2 dim, 2 dim) ``F`` of a constant-velocity step of ``dt`` seconds."""
    F = np.eye(2 * dim)
    F[:dim, dim:] = dt * np.eye(dim)
    return F


def process_noise(dt: float, accel_std: float | np.ndarray, dim: int) -> np.ndarray:
    """(2 dim, 2 dim) ``Q`` of the step (``accel_std``: one value, or (dim,) per coordinate)."""
    var = np.broadcast_to(np.asarray(accel_std, np.float64) ** 2, (dim,))
    blocks = np.array([[dt**4 / 4, dt**3 / 2], [dt**3 / 2, dt**2]])
    return np.kron(blocks, np.diag(var))


def predict(
    x: np.ndarray, P: np.ndarray, dt: float, accel_std: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The filters ``dt`` seconds later: ``x`` (T, 2 d), ``P`` (T, 2 d, 2 d) -> same shapes."""
    dim = x.shape[-1] // 2
    return predict_with(x, P, transition(dt, dim), process_noise(dt, accel_std, dim))


def predict_with(
    x: np.ndarray, P: np.ndarray, F: np.ndarray, Q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`predict` with the step's ``F`` and ``Q`` (2 d, 2 d) given."""
    return x @ F.T, F @ P @ F.T + Q


def innovation(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Residual ``z - H x`` (T, d) and its covariance ``S = H P H^T + R`` (T, d, d) of
    measurements ``z`` (T, d) with covariances ``R`` (T, d, d)."""
    dim = z.shape[-1]
    return z - x[:, :dim], P[:, :dim, :dim] + R


def update(
    x: np.ndarray, P: np.ndarray, z: np.ndarray, R: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The filters after measuring positions ``z`` (T, d) with covariances ``R`` (T, d, d).

    Gain ``K = P H^T S^-1``; ``x + K y``; Joseph form ``(I - K H) P (I - K H)^T + K R K^T``
    (stays symmetric and positive definite)."""
    dim = z.shape[-1]
    y, S = innovation(x, P, z, R)
    PHt = P[:, :, :dim]  # (T, 2d, d)
    K = np.linalg.solve(S, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)  # S symmetric
    x_new = x + np.einsum("tij,tj->ti", K, y)
    I_KH = np.broadcast_to(np.eye(2 * dim), P.shape).copy()
    I_KH[:, :, :dim] -= K
    P_new = I_KH @ P @ I_KH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)
    return x_new, P_new


def initial_state(
    z: np.ndarray, R: np.ndarray, speed_std: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """New filters at measured positions ``z`` (T, d) (covariance ``R`` (T, d, d)), at rest
    with velocity standard deviation ``speed_std`` per coordinate."""
    t, dim = z.shape
    x = np.concatenate([z, np.zeros_like(z)], axis=1)
    P = np.zeros((t, 2 * dim, 2 * dim))
    P[:, :dim, :dim] = R
    var = np.broadcast_to(np.asarray(speed_std, np.float64) ** 2, (dim,))
    P[:, dim:, dim:] = np.diag(var)
    return x, P
