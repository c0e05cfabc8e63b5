"""A road's centre line made of pieces of constant curvature, and motion along it.

A clip's world is built in road coordinates ``(t, y, s)`` (t lateral, right positive; y
down; s along the centre line, metres; see :mod:`scene`). A :class:`RoadPath` bends them
into the *world road frame* ``(x, y, z)``: the road frame of a straight road whose
centre line is the tangent at ``s = 0`` (x right, y down, z forward)::

    world(t, y, s) = C(s) + t n(s) + y e_y,   C' = (sin theta, cos theta),  theta' = kappa

with ``theta(0) = 0``, ``C(0) = 0`` and ``n = (cos theta, -sin theta)`` (in ``(x, z)``);
``kappa > 0`` turns right. The road keeps one flat ground plane; only its direction turns.

:class:`SpeedProfile` is a speed along a path over time (piecewise linear between knots),
:class:`Motion` the road-frame motion ``(t, s, psi)`` of a road user or the ego vehicle.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from gac_jax.geometry import rotation_y_matrix, wrap_angle


@dataclasses.dataclass(frozen=True)
class RoadPath:
    """Centre line: piece ``i`` starts at ``starts[i]`` (``starts[0]`` is ignored: the
    first piece reaches back to -inf) and has curvature ``curvatures[i]`` (1/m)."""

    starts: tuple[float, ...] = (0.0,)
    curvatures: tuple[float, ...] = (0.0,)

    def __post_init__(self):
        # heading and centre-line point where each piece starts (piece 0: at s = 0)
        theta, corner, origins = [0.0], [np.zeros(2)], [0.0]
        for i in range(1, len(self.starts)):
            s0, s1 = origins[-1], self.starts[i]
            c, th = self._advance(corner[-1], theta[-1], self.curvatures[i - 1], s1 - s0)
            theta.append(th)
            corner.append(c)
            origins.append(s1)
        object.__setattr__(self, "_theta", np.array(theta))
        object.__setattr__(self, "_corner", np.array(corner))
        object.__setattr__(self, "_origin", np.array(origins))

    @property
    def straight(self) -> bool:
        return not any(self.curvatures)

    @staticmethod
    def _advance(corner, theta, kappa, ds):
        ds = np.asarray(ds, np.float64)
        if kappa == 0.0:
            step = np.stack([np.sin(theta) * ds, np.cos(theta) * ds], -1)
            return corner + step, theta + 0.0 * ds
        th = theta + kappa * ds
        step = np.stack([np.cos(theta) - np.cos(th), np.sin(th) - np.sin(theta)], -1) / kappa
        return corner + step, th

    def _piece(self, s: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(np.array(self.starts[1:]), s, side="right"), 0, None)

    def heading(self, s) -> np.ndarray:
        """Direction ``theta`` of the centre line at ``s`` (radians about y, 0 = +z)."""
        s = np.asarray(s, np.float64)
        i = self._piece(s)
        return self._theta[i] + np.asarray(self.curvatures)[i] * (s - self._origin[i])

    def curvature(self, s) -> np.ndarray:
        return np.asarray(self.curvatures)[self._piece(np.asarray(s, np.float64))]

    def point(self, t, s) -> np.ndarray:
        """World ``(x, z)`` (..., 2) of road positions ``(t, s)``."""
        s = np.asarray(s, np.float64)
        i = self._piece(s)
        out = np.zeros((*s.shape, 2))
        for piece in np.unique(i):
            sel = i == piece
            c, th = self._advance(
                self._corner[piece],
                self._theta[piece],
                self.curvatures[piece],
                s[sel] - self._origin[piece],
            )
            out[sel] = c
        th = self.heading(s)
        return out + np.asarray(t, np.float64)[..., None] * np.stack([np.cos(th), -np.sin(th)], -1)

    def frame(self, s: float) -> tuple[np.ndarray, np.ndarray]:
        """``(R, C)``: world = ``R @ (t, y, 0) + C`` near ``s`` (R (3, 3), C (3,))."""
        x, z = self.point(0.0, s)
        return rotation_y_matrix(float(self.heading(s))), np.array([x, 0.0, z])

    def bend(self, solid):
        """A road-frame solid moved rigidly into the world at the middle of its ``s`` extent."""
        s = 0.5 * (solid.vertices[:, 2].min() + solid.vertices[:, 2].max())
        R, C = self.frame(s)
        return solid.transformed(R, C - R @ np.array([0.0, 0.0, s]))

    def to_road(self, x: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Road positions ``(t, s)`` of world points ``(x, z)`` (n,): the nearest piece's."""
        x, z = np.asarray(x, np.float64), np.asarray(z, np.float64)
        bounds = [-np.inf, *self.starts[1:], np.inf]
        best_t, best_s = np.zeros_like(x), np.zeros_like(x)
        best = np.full(x.shape, np.inf)
        for i, kappa in enumerate(self.curvatures):
            th0, (cx, cz), s0 = self._theta[i], self._corner[i], self._origin[i]
            if kappa == 0.0:
                dx, dz = x - cx, z - cz
                s = s0 + dx * np.sin(th0) + dz * np.cos(th0)
                t = dx * np.cos(th0) - dz * np.sin(th0)
            else:  # polar about the centre of the arc
                ox, oz = cx + np.cos(th0) / kappa, cz - np.sin(th0) / kappa
                dx, dz = x - ox, z - oz
                r = np.hypot(dx, dz)
                sign = np.sign(kappa)
                th = np.arctan2(sign * dz, -sign * dx)  # n = -sign d / r = (cos th, -sin th)
                s = s0 + wrap_angle(th - th0) / kappa
                t = 1.0 / kappa - sign * r
            outside = np.maximum(bounds[i] - s, 0.0) + np.maximum(s - bounds[i + 1], 0.0)
            cost = np.abs(t) + 1e3 * outside
            take = cost < best
            best = np.where(take, cost, best)
            best_t = np.where(take, t, best_t)
            best_s = np.where(take, s, best_s)
        return best_t, best_s

    def velocity(self, t, s, vt, vs) -> np.ndarray:
        """World ``(vx, vz)`` of a point at ``(t, s)`` moving at road rates ``(vt, vs)``."""
        th = self.heading(s)
        along = np.asarray(vs) * (1.0 - self.curvature(s) * np.asarray(t))
        return np.stack(
            [np.cos(th) * vt + np.sin(th) * along, -np.sin(th) * vt + np.cos(th) * along], -1
        )


@dataclasses.dataclass(frozen=True)
class SpeedProfile:
    """Speed (m/s) over time (s): linear between the knots, constant before and after."""

    times: tuple[float, ...] = (0.0,)
    speeds: tuple[float, ...] = (0.0,)

    def speed(self, time) -> np.ndarray:
        return np.interp(np.asarray(time, np.float64), self.times, self.speeds)

    def distance(self, time) -> np.ndarray:
        """Metres covered from time 0 (``times[0]``) to ``time``, exactly."""
        tk, vk = np.asarray(self.times, np.float64), np.asarray(self.speeds, np.float64)
        tau = np.asarray(time, np.float64)
        cum = np.concatenate([[0.0], np.cumsum(0.5 * (vk[1:] + vk[:-1]) * np.diff(tk))])
        i = np.clip(np.searchsorted(tk, tau, side="right") - 1, 0, len(tk) - 1)
        dt = tau - tk[i]
        slope = np.append(np.diff(vk) / np.diff(tk), 0.0)
        slope = np.where(dt < 0, 0.0, slope[i])
        return cum[i] + vk[i] * dt + 0.5 * slope * dt * dt


@dataclasses.dataclass(frozen=True)
class Motion:
    """Road-frame motion: lane travel at a speed profile, a lane change, a lateral walk.

    ``s = s0 + direction * profile.distance(time)``; ``t = clip(t0 + vt time, *t_range)``
    plus, with ``lane_change = (dt, start, duration)``, ``dt`` reached smoothly (half a
    cosine) from ``start`` to ``start + duration`` seconds. The heading is ``psi0`` turned
    towards the velocity while changing lanes.
    """

    t0: float
    s0: float
    psi0: float
    direction: float = 0.0  # +1 along +s, -1 against it, 0 no travel along the road
    profile: SpeedProfile = SpeedProfile()
    vt: float = 0.0
    t_range: tuple[float, float] = (-np.inf, np.inf)
    lane_change: tuple[float, float, float] | None = None

    def _lane(self, time):
        if self.lane_change is None:
            return 0.0 * time, 0.0 * time
        dt, start, duration = self.lane_change
        u = np.clip((time - start) / duration, 0.0, 1.0)
        rate = np.where((u > 0) & (u < 1), dt * np.pi / (2 * duration) * np.sin(np.pi * u), 0.0)
        return dt * 0.5 * (1.0 - np.cos(np.pi * u)), rate

    def at(self, time) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(t, s, psi)`` at ``time`` (array or scalar; same shape)."""
        time = np.asarray(time, np.float64)
        lo, hi = self.t_range
        shift, rate = self._lane(time)
        t = np.clip(self.t0 + self.vt * time, lo, hi) + shift
        s = self.s0 + self.direction * self.profile.distance(time)
        psi = self.psi0 + 0.0 * time
        if self.lane_change is not None:
            speed = self.profile.speed(time)
            psi = psi + self.direction * np.arctan2(rate, speed + 1e-9)
        return t, s, psi

    def rates(self, time) -> tuple[np.ndarray, np.ndarray]:
        """Road rates ``(dt/dtime, ds/dtime)`` (m/s) at ``time``."""
        time = np.asarray(time, np.float64)
        lo, hi = self.t_range
        free = self.t0 + self.vt * time
        vt = np.where((free > lo) & (free < hi), self.vt, 0.0) + self._lane(time)[1]
        return vt, self.direction * self.profile.speed(time)
