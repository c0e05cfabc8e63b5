"""Ray-casting rasteriser for scenes of convex solids over a ground plane, with a z-buffer.

Every pixel centre ``(u, v)`` (integer coordinates, KITTI's convention) sees the
ray ``X(w) = C + w r(u, v)`` with ``r = M^-1 [u, v, 1]`` (``P = [M | p]``,
``C`` the optical centre) and ``w`` the camera's depth (``z`` of that camera).
For a plane ``n . X = d`` the inverse depth ``rho = 1 / w`` of the intersection
is affine in ``(u, v)``: ``rho = (n . r) / (d - n . C)``. A convex solid is the
intersection of half-spaces, so a ray is inside it for
``max_back q_k <= rho <= min_front q_k`` (front: faces the camera sees from
outside), and the visible point is ``rho = min_front q_k``. This gives exact
per-pixel depth and exact pixel-centre coverage with two array operations per
face, evaluated only inside the solid's screen rectangle.

The z-buffer stores inverse depth; the ground plane seeds it and the sky is 0.
"""

from __future__ import annotations

import dataclasses
import functools

import cv2
import numpy as np

from gac_jax.data.synthetic import materials, shapes
from gac_jax.data.synthetic.scene import Scene
from gac_jax.geometry import camera_center, project

NEAR = 0.05  # metres
MAX_DEPTH = 250.0  # depth maps hold 0 beyond this (16-bit KITTI PNGs saturate at 256 m)
SKY, GROUND, RECEIVER, SURFACE = 0, 1, 2, 3  # surface kinds (receivers take shadows)


@dataclasses.dataclass
class ViewRender:
    """One camera's render of a scene.

    Attributes:
      image: (H, W, 3) uint8 RGB.
      depth: (H, W) float32 depth (z of this camera) in metres, 0 = sky / beyond MAX_DEPTH.
      object_ids: (H, W) int16 index into ``scene.objects`` of the visible object, -1 elsewhere.
      silhouette_px: (N,) pixels of each object's own silhouette inside the image
        (as if nothing else were there).
      surface: (H, W) uint8 what each pixel shows: ``SKY``, ``GROUND`` (the road
        plane), ``RECEIVER`` (sidewalk tops) or ``SURFACE`` (any other solid).
    """

    image: np.ndarray
    depth: np.ndarray
    object_ids: np.ndarray
    silhouette_px: np.ndarray
    surface: np.ndarray


@dataclasses.dataclass(frozen=True)
class Camera:
    """A projection and the quantities the ray caster needs."""

    P: np.ndarray  # (3, 4)
    size: tuple[int, int]  # (H, W)

    @functools.cached_property
    def Minv(self) -> np.ndarray:
        """(3, 3) inverse of ``P[:, :3]``: ``r = Minv @ [u, v, 1]`` is the ray per unit depth."""
        return np.linalg.inv(self.P[:, :3])

    @functools.cached_property
    def C(self) -> np.ndarray:
        """(3,) optical centre."""
        return camera_center(self.P)


def screen_rect(vertices: np.ndarray, P: np.ndarray, bounds) -> tuple[int, int, int, int] | None:
    """Integer pixel rectangle ``(u0, u1, v0, v1)`` (inclusive) covering a convex solid.

    The part of the solid behind the near plane is cut off (the crossings of
    all vertex pairs bound the section). ``bounds = (u_min, u_max, v_min, v_max)``
    clips the result; None when the solid is not in front or misses ``bounds``.
    """
    uv, w = project(vertices, P)
    front = w > NEAR
    pts = uv[front]
    if not front.all():
        i, j = np.triu_indices(len(vertices), 1)
        cross = (w[i] - NEAR) * (w[j] - NEAR) < 0
        if cross.any():
            a, b = vertices[i[cross]], vertices[j[cross]]
            t = (NEAR - w[i[cross]]) / (w[j[cross]] - w[i[cross]])
            pts = np.concatenate([pts, project(a + t[:, None] * (b - a), P)[0]])
    if len(pts) == 0:
        return None
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    u0, u1 = max(int(np.ceil(lo[0])), bounds[0]), min(int(np.floor(hi[0])), bounds[1])
    v0, v1 = max(int(np.ceil(lo[1])), bounds[2]), min(int(np.floor(hi[1])), bounds[3])
    if u0 > u1 or v0 > v1:
        return None
    return u0, u1, v0, v1


def cast(solid: shapes.Solid, cam: Camera, rect, stride: int = 1):
    """Casts the rays of the pixels in ``rect`` (every ``stride``-th) against ``solid``.

    Returns:
      hit: (h, w) bool, the ray meets the solid in front of the camera;
      rho: (h, w) float32 inverse depth of the visible point (valid where hit);
      face: (h, w) index of the visible face (valid where hit).
    """
    u0, u1, v0, v1 = rect
    C, Minv = cam.C, cam.Minv
    num = solid.offsets - solid.normals @ C  # < 0: camera outside that face's half-space
    # q_k(u, v) = coef_k . [u, v, 1]. A face whose plane passes through the camera (num 0,
    # e.g. a multi-rig camera exactly at a box's top height) is seen edge-on: its
    # coefficients are +-inf, and the comparisons below then keep or drop whole rays as
    # that face's half-space does (a ray exactly in the plane gives nan: a miss), so the
    # division warnings say nothing wrong.
    with np.errstate(divide="ignore", invalid="ignore"):
        coef = (solid.normals @ Minv) / num[:, None]
    U = np.arange(u0, u1 + 1, stride, dtype=np.float32)[None, :]
    V = np.arange(v0, v1 + 1, stride, dtype=np.float32)[:, None]
    front = np.flatnonzero(num < 0)
    back = np.flatnonzero(num >= 0)
    if len(front) == 0:  # the camera is inside the solid: nothing of it is seen from outside
        shape = (len(V), U.shape[1])
        return np.zeros(shape, bool), np.zeros(shape, np.float32), np.zeros(shape, np.int8)
    cf = coef[front].astype(np.float32)
    rho = cf[0, 0] * U + (cf[0, 1] * V + cf[0, 2])
    face = np.full(rho.shape, front[0], np.int8)
    for k in range(1, len(front)):
        q = cf[k, 0] * U + (cf[k, 1] * V + cf[k, 2])
        nearer = q < rho
        np.copyto(rho, q, where=nearer)
        np.copyto(face, np.int8(front[k]), where=nearer)
    hit = rho > 0
    cb = coef[back].astype(np.float32)
    with np.errstate(invalid="ignore"):  # inf - inf of an edge-on face: nan, not a hit
        for k in range(len(back)):
            hit &= rho >= cb[k, 0] * U + (cb[k, 1] * V + cb[k, 2])
    return hit, rho, face


def _points(cam: Camera, u: np.ndarray, v: np.ndarray, rho: np.ndarray) -> np.ndarray:
    """(n, 3) float32 camera-frame points seen at pixels ``(u, v)`` with inverse depth ``rho``."""
    Minv, C = cam.Minv.astype(np.float32), cam.C.astype(np.float32)
    w = 1.0 / rho
    cols = [C[i] + (Minv[i, 0] * u + Minv[i, 1] * v + Minv[i, 2]) * w for i in range(3)]
    return np.stack(cols, axis=-1)


class _Canvas:
    """The frame buffers of one view (deferred shading).

    Drawing a solid only z-buffers it: per pixel the inverse depth, a global
    face id (index into the faces of all drawn solids, -1 = ground or sky) and
    the object id. :meth:`shade` then colours every pixel once.
    """

    def __init__(self, scene: Scene, cam: Camera):
        H, W = cam.size
        self.scene, self.cam = scene, cam
        self.bounds = (0, W - 1, 0, H - 1)
        v = np.arange(H, dtype=np.float64)
        n, h = scene.ground_normal, scene.camera_height
        coef = (n @ cam.Minv) / (h - n @ cam.C)  # ground rho = coef . [u, v, 1]
        # no camera roll: the ground's inverse depth is the same along each row
        assert abs(coef[0]) < 1e-12, "camera roll is not supported"
        ground_rho = (coef[1] * v + coef[2]).astype(np.float32)
        ground_rho[ground_rho <= 0] = 0.0
        self.zbuf = np.repeat(ground_rho[:, None], W, axis=1)
        self.gid = np.full((H, W), -1, np.int32)
        self.ids = np.full((H, W), -1, np.int16)
        self.drawn: list[tuple[shapes.Solid, int, tuple]] = []  # (solid, first face id, rect)
        self.num_faces = 0

    def face_colors(self, solid: shapes.Solid) -> np.ndarray:
        """(K, 3) Lambert-shaded colours of the solid's faces."""
        s = self.scene
        diffuse = np.maximum(solid.normals @ s.sun, 0.0) * (1.0 - s.ambient)
        out = solid.colors * (s.ambient + diffuse)[:, None]
        if solid.gloss > 0:  # the sky mirrored: the zenith in upward faces, the horizon sideways
            up = np.clip(-(solid.normals @ s.ground_normal), 0.0, 1.0)
            side = 1.0 - np.abs(solid.normals @ s.ground_normal)
            sky = up[:, None] * s.sky_top + 0.5 * side[:, None] * s.sky_horizon
            out = out * (1.0 - solid.gloss) + solid.gloss * sky
            out[solid.materials == shapes.GLASS] = (solid.colors * (s.ambient + diffuse)[:, None])[
                solid.materials == shapes.GLASS
            ]
        return out.astype(np.float32)

    def draw(self, solid: shapes.Solid, object_id: int = -1, rect=None, union=None) -> None:
        """Z-buffers ``solid``; ``union`` (bool array over ``rect``) gathers its coverage."""
        sub = screen_rect(solid.vertices, self.cam.P, self.bounds if rect is None else rect)
        if sub is None:
            return
        u0, u1, v0, v1 = sub
        hit, rho, face = cast(solid, self.cam, sub)
        if union is not None:
            union[v0 - rect[2] : v1 - rect[2] + 1, u0 - rect[0] : u1 - rect[0] + 1] |= hit
        window = (slice(v0, v1 + 1), slice(u0, u1 + 1))
        zb = self.zbuf[window]
        win = hit & (rho > zb)
        if not win.any():
            return
        np.copyto(zb, rho, where=win)
        np.copyto(self.gid[window], np.add(face, self.num_faces, dtype=np.int32), where=win)
        if object_id >= 0:  # (the background is drawn first, over ids that are all -1)
            np.copyto(self.ids[window], np.int16(object_id), where=win)
        self.drawn.append((solid, self.num_faces, sub))
        self.num_faces += len(solid.offsets)

    def shade(self) -> tuple[np.ndarray, np.ndarray]:
        """Colours every pixel; returns the (H, W, 3) float32 image and the surface-kind map."""
        H, W = self.cam.size
        solids = [d[0] for d in self.drawn]
        table = np.concatenate(
            [self.face_colors(s) for s in solids] + [np.zeros((1, 3), np.float32)]
        )
        image = table[self.gid]
        receiver = np.concatenate([s.materials == shapes.PAVING for s in solids] + [[False]])
        kind = np.where(receiver[self.gid], RECEIVER, SURFACE).astype(np.uint8)
        background = self.gid < 0
        kind[background & (self.zbuf > 0)] = GROUND
        kind[background & (self.zbuf == 0)] = SKY
        sky_px = kind == SKY
        if sky_px.any():
            image[sky_px] = self._sky_rows()[np.nonzero(sky_px)[0]]
        for solid, first, (u0, u1, v0, v1) in self.drawn:
            if np.all(solid.materials == shapes.FLAT):
                continue
            g = self.gid[v0 : v1 + 1, u0 : u1 + 1]
            rr, cc = np.nonzero((g >= first) & (g < first + len(solid.offsets)))
            if len(rr) == 0:
                continue
            f = g[rr, cc] - first
            rr += v0
            cc += u0
            r_win = self.zbuf[rr, cc]
            pts = _points(self.cam, cc.astype(np.float32), rr.astype(np.float32), r_win)
            frame = solid.frame.astype(np.float32)
            d = [pts[:, i] - frame[i, 3] for i in range(3)]
            local = np.stack(
                [d[0] * frame[0, k] + d[1] * frame[1, k] + d[2] * frame[2, k] for k in range(3)], -1
            )
            image[rr, cc] = materials.textured_faces(
                solid, f, local, 1.0 / r_win, image[rr, cc], float(self.cam.P[0, 0])
            )
        self.image, self.kind = image, kind
        self.shade_ground()
        self.shadows()
        return self.image, self.kind

    def _sky_rows(self) -> np.ndarray:
        cam, scene = self.cam, self.scene
        H = cam.size[0]
        v = np.arange(H, dtype=np.float64)
        ray = (cam.Minv @ np.stack([np.full(H, cam.P[0, 2]), v, np.ones(H)])).T
        level = ray @ scene.road_rotation  # directions in the road frame (y down)
        elevation = np.arctan2(-level[:, 1], np.hypot(level[:, 0], level[:, 2]))
        return materials.sky_rows(elevation, scene.sky_top, scene.sky_horizon)

    def shade_ground(self) -> None:
        rr, cc = np.nonzero(self.kind == GROUND)
        if rr.size == 0:  # no road surface in view (a narrow street, a vehicle close ahead)
            return
        cam, scene = self.cam, self.scene
        depth = 1.0 / self.zbuf[rr, cc]
        u, v = cc.astype(np.float32), rr.astype(np.float32)
        # road coordinates of the ground points: origin + (R^T M^-1 [u, v, 1]) * depth
        R = scene.road_rotation
        A = (R.T @ cam.Minv).astype(np.float32)
        o = (R.T @ (cam.C - scene.road_translation)).astype(np.float32)
        t = o[0] + (A[0, 0] * u + A[0, 1] * v + A[0, 2]) * depth
        s = o[2] + (A[2, 0] * u + A[2, 1] * v + A[2, 2]) * depth
        if scene.path is not None:  # world road frame -> along the curved road
            t, s = (c.astype(np.float32) for c in scene.path.to_road(t, s))
        fx, fy = cam.P[0, 0], cam.P[1, 1]
        px_lat = depth * np.float32(1.0 / fx)
        # along the road one pixel spans depth^2 / (f h) metres of ground
        px_long = np.maximum(depth * px_lat * np.float32(fx / (fy * scene.camera_height)), px_lat)
        col = materials.road_surface(scene.road, t, s, depth, px_lat, px_long)
        light = scene.ambient + (1.0 - scene.ambient) * max(-scene.ground_normal @ scene.sun, 0.0)
        self.image[rr, cc] = col * np.float32(light)

    def shadows(self) -> None:
        """Shadows on the ground and sidewalks: soft-edged ones of the road users, and the
        exact ones of the roadside's solids (buildings, trees, poles, barriers)."""
        scene, cam = self.scene, self.cam
        sun_road = scene.sun @ scene.road_rotation
        H, W = cam.size
        mask = np.zeros((H, W), np.float32)
        for solid in scene.background:
            hull = ground_shadow(
                solid.vertices, scene.sun, scene.ground_normal, scene.camera_height, cam.P
            )
            if hull is not None:
                cv2.fillConvexPoly(mask, hull, 1.0, lineType=cv2.LINE_AA, shift=2)
        contact = np.zeros((H, W), np.float32)  # the dark ground right under a road user
        for obj in scene.objects:
            foot = scene.to_road(obj.corners()[:4])
            foot[:, 1] = obj.support_y
            centre = foot.mean(axis=0)
            under = centre + (foot - centre) * np.array([0.92, 1.0, 0.95])
            uv, w = project(under @ scene.road_rotation.T + scene.road_translation, cam.P)
            if np.all(w >= NEAR):
                hull = cv2.convexHull(np.round(uv * 4).astype(np.int32))
                cv2.fillConvexPoly(contact, hull, 1.0, lineType=cv2.LINE_AA, shift=2)
            grown = centre + (foot - centre) * 1.08
            elev = max(-sun_road[1], 0.2)
            shift = -sun_road / elev * obj.dimensions[0] * 0.6
            shift[1] = 0.0
            poly = np.concatenate([grown, grown + shift])
            world = poly @ scene.road_rotation.T + scene.road_translation
            uv, w = project(world, cam.P)
            if np.any(w < NEAR):
                continue
            hull = cv2.convexHull(np.round(uv * 4).astype(np.int32))
            cv2.fillConvexPoly(mask, hull, 1.0, lineType=cv2.LINE_AA, shift=2)
        receivers = (self.kind == GROUND) | (self.kind == RECEIVER)
        dark = np.maximum(scene.shadow * mask, CONTACT_SHADOW * contact)
        self.image *= (1.0 - dark * receivers)[:, :, None]


CONTACT_SHADOW = 0.7  # darkening of the ground under a road user, whatever the sky
MIN_CASTER_HEIGHT = 0.3  # metres: lower solids (kerbs, sidewalk slabs) cast no shadow


def ground_shadow(vertices, sun, normal, height, P) -> np.ndarray | None:
    """The image polygon of a convex solid's shadow on the ground plane, or None.

    The shadow of a convex solid on a plane is the convex hull of its vertices moved
    along the light, ``X - k sun`` with ``n . (X - k sun) = height`` (camera frame:
    ``sun`` (3,) towards the sun, ``n`` the ground's downward unit normal); vertices below
    the ground (foundations) are moved straight up onto it. The hull is
    clipped to the half-space in front of the camera (``z >= NEAR``) before projection.

    Returns:
      (K, 1, 2) int32 hull in pixel units x 4 (``cv2.fillConvexPoly(..., shift=2)``), or
      None for a solid lower than MIN_CASTER_HEIGHT, under a sun at the horizon, or a
      shadow wholly behind the camera.
    """
    v = np.asarray(vertices, np.float64)
    above = height - v @ normal  # height of each vertex above the ground
    n_sun = float(normal @ sun)
    if above.max() < MIN_CASTER_HEIGHT or n_sun > -0.05:
        return None
    k = -np.maximum(above, 0.0) / n_sun
    pts = v - k[:, None] * sun[None, :]
    below = above < 0  # (foundations under the ground: straight up onto it)
    pts[below] = v[below] + above[below, None] * normal[None, :]
    # the hull in the plane, in order: 2D hull of the points in plane coordinates
    e1 = np.cross(normal, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    hull = cv2.convexHull(np.stack([pts @ e1, pts @ e2], 1).astype(np.float32), returnPoints=False)
    poly = _clip_near(pts[hull[:, 0]], NEAR)
    if len(poly) < 3:
        return None
    uv, _ = project(poly, P)
    return np.round(uv * 4).astype(np.int32).reshape(-1, 1, 2)


def _clip_near(poly: np.ndarray, near: float) -> np.ndarray:
    """Clips a convex polygon (K, 3) (camera frame, in order) to ``z >= near``."""
    out = []
    for i in range(len(poly)):
        a, b = poly[i], poly[(i + 1) % len(poly)]
        if a[2] >= near:
            out.append(a)
        if (a[2] >= near) != (b[2] >= near):
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out).reshape(-1, 3)


def render_view(
    scene: Scene, P: np.ndarray, image_size: tuple[int, int], rng: np.random.Generator
) -> ViewRender:
    """Renders ``scene`` through the projection ``P`` (3, 4) into an image of ``(H, W)``.

    ``rng`` draws the sensor noise (the only randomness of the camera).
    """
    cam = Camera(np.asarray(P, np.float64), tuple(image_size))
    canvas = _Canvas(scene, cam)
    for solid in scene.background:
        canvas.draw(solid)
    silhouette = np.zeros(len(scene.objects), np.int64)
    for i, obj in enumerate(scene.objects):
        verts = np.concatenate([p.vertices for p in obj.parts])
        rect = screen_rect(verts, cam.P, canvas.bounds)
        if rect is None:
            continue
        union = np.zeros((rect[3] - rect[2] + 1, rect[1] - rect[0] + 1), bool)
        for part in obj.parts:
            canvas.draw(part, i, rect, union)
        silhouette[i] = int(union.sum())
    color, kind = canvas.shade()
    depth = np.zeros(cam.size, np.float32)
    valid = canvas.zbuf > np.float32(1.0 / MAX_DEPTH)
    depth[valid] = 1.0 / canvas.zbuf[valid]
    image = _expose(color, scene, rng)
    return ViewRender(image, depth, canvas.ids, silhouette, kind)


def silhouette_outside(obj_parts, P: np.ndarray, image_size, max_samples: int = 60000) -> float:
    """Area (pixels) of an object's silhouette outside the image (sampled on a grid).

    The silhouette is considered within ``[-2W, 3W] x [-2H, 3H]``.
    """
    H, W = image_size
    cam = Camera(np.asarray(P, np.float64), (H, W))
    verts = np.concatenate([p.vertices for p in obj_parts])
    rect = screen_rect(verts, P, (-2 * W, 3 * W, -2 * H, 3 * H))
    if rect is None:
        return 0.0
    u0, u1, v0, v1 = rect
    if u0 >= 0 and v0 >= 0 and u1 <= W - 1 and v1 <= H - 1:
        return 0.0
    area = (u1 - u0 + 1) * (v1 - v0 + 1)
    stride = max(1, int(np.ceil(np.sqrt(area / max_samples))))
    U = np.arange(u0, u1 + 1, stride)
    V = np.arange(v0, v1 + 1, stride)
    union = np.zeros((len(V), len(U)), bool)
    for part in obj_parts:
        union |= cast(part, cam, rect, stride)[0]
    outside = ~(((U >= 0) & (U <= W - 1))[None, :] & ((V >= 0) & (V <= H - 1))[:, None])
    return float((union & outside).sum()) * stride * stride


def _expose(image: np.ndarray, scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """Camera response, drawn per view from ``rng``: exposure and white balance, sensor
    noise of random strength, defocus and (sometimes) motion blur, lateral chromatic
    aberration, vignetting, a tone curve, 8-bit output."""
    ev = float(np.clip(2.0 ** rng.normal(0.0, 0.3), 0.6, 1.6))  # exposure error
    img = image * (scene.exposure * np.float32(255.0 * ev))
    H, W = img.shape[:2]
    noise = _sensor_noise(H, W)
    y0, x0 = (
        int(rng.integers(0, noise.shape[0] - H + 1)),
        int(rng.integers(0, noise.shape[1] - W + 1)),
    )
    img += noise[y0 : y0 + H, x0 : x0 + W] * np.float32(rng.uniform(0.5, 2.5))
    # (the noise is blurred too, like demosaicing does)
    img = cv2.GaussianBlur(img, (5, 5), float(rng.uniform(0.45, 1.1)))
    if rng.random() < 0.3:  # motion blur along the rows
        k = int(rng.integers(2, 5))
        img = cv2.blur(img, (k, 1))
    if rng.random() < 0.5:  # lateral chromatic aberration: red and blue scaled about the centre
        c = float(rng.uniform(0.0005, 0.002))
        for ch, scale in ((0, 1.0 + c), (2, 1.0 - c)):
            A = np.array([[scale, 0, (1 - scale) * W / 2], [0, scale, (1 - scale) * H / 2]])
            img[..., ch] = cv2.warpAffine(
                img[..., ch], A, (W, H), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT
            )
    strength = float(rng.uniform(0.0, 0.35))
    if strength > 0:
        img *= _vignette(H, W, strength)[:, :, None]
    gamma = float(rng.uniform(0.8, 1.25))
    np.clip(img, 0.0, 255.0, out=img)
    img = np.float32(255.0) * (img * np.float32(1.0 / 255.0)) ** np.float32(gamma)
    return img.astype(np.uint8)


def _vignette(height: int, width: int, strength: float) -> np.ndarray:
    """(H, W) float32 gain ``1 - strength * (r / r_corner)^2`` about the image centre."""
    v = (np.arange(height, dtype=np.float32) - (height - 1) / 2) ** 2
    u = (np.arange(width, dtype=np.float32) - (width - 1) / 2) ** 2
    r2 = (v[:, None] + u[None, :]) / np.float32(v.max() + u.max())
    return np.float32(1.0) - np.float32(strength) * r2


@functools.cache
def _sensor_noise_field(height: int, width: int) -> np.ndarray:
    rng = np.random.default_rng(7)
    return rng.normal(0.0, 2.0, (height, width, 3)).astype(np.float32)


def _sensor_noise(height: int, width: int) -> np.ndarray:
    """A fixed field of sensor noise (std 2 grey levels) a little larger than the image."""
    return _sensor_noise_field(height + 64, width + 64)
