"""Surface appearance: sky, road surface and textured faces, as functions of 3D position.

Textures are looked up by metric surface coordinates, so their detail shrinks
with distance exactly as the geometry does (a depth cue, like real asphalt
grain). Fine texture is faded with distance and painted lines are given soft,
coverage-based edges, so far surfaces do not alias into noise.

All colours are float32 RGB in [0, 1] before the camera's exposure.
"""

from __future__ import annotations

import functools

import numpy as np

from gac_jax.data.synthetic import photo_textures, shapes

TILE = 256  # noise tiles are TILE x TILE and wrap around


@functools.cache
def noise_tiles() -> dict[str, np.ndarray]:
    """Periodic band-limited noise tiles (float32, zero mean, unit std), equal in every process."""
    rng = np.random.default_rng(20210401)
    freq = np.fft.fftfreq(TILE)
    radius = np.hypot(freq[:, None], freq[None, :])
    tiles = {}
    for name, cutoff in (("fine", 0.25), ("medium", 0.06)):
        spectrum = np.fft.fft2(rng.standard_normal((TILE, TILE)))
        field = np.real(np.fft.ifft2(spectrum * np.exp(-((radius / cutoff) ** 2))))
        field = (field - field.mean()) / field.std()
        tiles[name] = field.astype(np.float32)
    return tiles


def lookup(tile: str, a: np.ndarray, b: np.ndarray, texels_per_metre: float) -> np.ndarray:
    """Samples a noise tile at metric coordinates ``(a, b)`` (nearest texel, wrapping)."""
    t = noise_tiles()[tile]
    ia = (a * texels_per_metre).astype(np.int32) & (TILE - 1)
    ib = (b * texels_per_metre).astype(np.int32) & (TILE - 1)
    return t[ia, ib]


def coverage(distance_inside: np.ndarray, pixel_size: np.ndarray) -> np.ndarray:
    """Fraction of a pixel covered by a shape, from the signed distance to its edge (metres)."""
    return np.clip(distance_inside / pixel_size + 0.5, 0.0, 1.0)


def hash01(i: np.ndarray, j: np.ndarray, salt: int) -> np.ndarray:
    """Deterministic pseudo-random values in [0, 1) for integer grid cells ``(i, j)``."""
    h = (i.astype(np.int64) * 73856093) ^ (j.astype(np.int64) * 19349663) ^ (salt * 83492791)
    h = (h ^ (h >> 13)) * 1274126177
    return ((h >> 8) & 0xFFFF).astype(np.float32) / 65536.0


def sky_rows(elevation: np.ndarray, top, horizon) -> np.ndarray:
    """(H, 3) sky colour per image row from the ray elevation (radians, up positive)."""
    x = np.clip(elevation / 0.45, 0.0, 1.0)[:, None] ** 0.7
    return (np.asarray(horizon) * (1.0 - x) + np.asarray(top) * x).astype(np.float32)


LUT_STEP = 0.02  # metres per entry of the lateral road profile


def road_surface(road, t, s, depth, px_lat, px_long) -> np.ndarray:
    """(n, 3) colours of ground points at road coordinates ``(t, s)`` (metres).

    Everything that varies only across the road (asphalt or verge colour,
    darker wheel tracks, which painted line is near) comes from a lateral
    look-up table; the rest is evaluated per pixel.

    Args:
      road: the scene's :class:`~gac_jax.data.synthetic.scene.Road`.
      t, s: (n,) lateral / along-road positions; depth: (n,) camera depth.
      px_lat, px_long: (n,) ground size of one pixel across / along the road.
    """
    lo = max(float(t.min()), -100.0) - LUT_STEP
    hi = min(float(t.max()), 100.0) + LUT_STEP
    grid = np.arange(lo, hi + LUT_STEP, LUT_STEP)
    on_road = (grid >= road.left) & (grid <= road.right)
    base = np.where(on_road[:, None], road.asphalt, road.verge_left).astype(np.float32)
    base[grid > road.right] = road.verge_right
    tracks = np.zeros_like(grid)
    for c in road.lane_centres:
        for off in (-0.8, 0.8):
            tracks += 0.05 * np.exp(-(((grid - c - off) / 0.35) ** 2))
    base *= (1.0 - tracks)[:, None].astype(np.float32)
    verge = np.where(on_road, 0.0, 1.0).astype(np.float32)
    nearest_mark = np.full(len(grid), -1, np.int32)
    for k, (tc, half, *_) in enumerate(road.markings):
        nearest_mark[np.abs(grid - tc) < half + 0.6] = k
    idx = ((np.clip(t, lo, hi) - lo) * np.float32(1.0 / LUT_STEP)).astype(np.int32)

    fade = np.clip(6.0 / depth, 0.15, 1.0)
    grain = lookup("fine", s, t, 24.0) * fade
    patch = lookup("medium", s, t, 6.0)
    if road.verge_photo is None:
        shade = 1.0 + 0.07 * grain + 0.06 * patch + verge[idx] * (0.15 * patch + 0.12 * grain)
    else:  # grass from a photograph on the verges (photo_textures)
        texture, metres, contrast, da, db = road.verge_photo[:5]
        shade = 1.0 + 0.07 * grain + 0.06 * patch
        sel = np.flatnonzero(verge[idx] > 0)
        footprint = np.sqrt(px_lat[sel] * px_long[sel])
        detail = photo_textures.sample(int(texture), t[sel] + da, s[sel] + db, metres, footprint)
        shade[sel] = 1.0 + 0.15 * patch[sel] + np.float32(contrast) * detail
    color = base[idx] * shade[:, None]

    paint = np.zeros_like(t)
    mark = nearest_mark[idx]
    sel = np.flatnonzero(mark >= 0)
    if len(sel):
        tc, half, period, dash, phase = (
            road.markings[mark[sel], i].astype(np.float32) for i in range(5)
        )
        cov = coverage(half - np.abs(t[sel] - tc), px_lat[sel])
        ds = np.mod(s[sel] - phase, np.maximum(period, 1e-3))
        dashed = coverage(np.minimum(ds, dash - ds), px_long[sel])
        paint[sel] = cov * np.where(period > 0, dashed, 1.0)
    if road.crosswalk is not None:
        s0, s1 = road.crosswalk
        sel = np.flatnonzero((s > s0 - 1) & (s < s1 + 1) & on_road[idx])
        cov = coverage(np.minimum(s[sel] - s0, s1 - s[sel]), px_long[sel])
        dt = np.mod(t[sel], 1.0)
        cov *= coverage(np.minimum(dt, 0.5 - dt), px_lat[sel])
        paint[sel] = np.maximum(paint[sel], cov)
    if road.cross is not None:  # a cross street: asphalt across, no lines in the junction
        c0, c1 = road.cross
        junction = (s > c0) & (s < c1)
        color[junction] = road.asphalt * (1.0 + 0.07 * grain + 0.06 * patch)[junction, None]
        paint[junction] = 0.0
    paint *= road.paint_strength * (1.0 + 0.15 * grain)
    return color * (1.0 - paint[:, None]) + road.paint_color * paint[:, None]


PAVING_TILE = 0.45  # metres


@functools.cache
def paving_texture() -> np.ndarray:
    """(64, 64) float32 brightness of one square paving tile with grout lines at its border."""
    x = (np.arange(64) + 0.5) / 64 * PAVING_TILE
    edge = np.minimum(x, PAVING_TILE - x)
    line = np.clip((edge - 0.012) / 0.008, 0.0, 1.0)
    return (0.72 + 0.28 * np.minimum(line[:, None], line[None, :])).astype(np.float32)


def textured_faces(
    solid: shapes.Solid, face: np.ndarray, local: np.ndarray, depth, base, focal: float = 721.5
):
    """Applies ``solid``'s textures to some of its pixels.

    Args:
      face: (n,) face index of each pixel; local: (n, 3) the pixel's 3D point in
        the solid's texture frame; depth: (n,) camera depth; base: (n, 3) flat
        shaded colours (modified and returned); focal: the camera's focal length
        (pixels), for the size of a pixel on a surface.
    """
    codes = set(solid.materials.tolist()) - {shapes.FLAT}
    mats = solid.materials[face] if len(codes) > 1 or shapes.FLAT in solid.materials else None
    fade = np.clip(5.0 / depth, 0.2, 1.0)
    for code in sorted(codes):
        sel = slice(None) if mats is None else np.flatnonzero(mats == code)
        x, y, z = local[sel, 0], local[sel, 1], local[sel, 2]
        if code == shapes.FACADE:
            base[sel] = _facade(solid.params, face[sel], x, y, z, base[sel], fade[sel])
        elif code == shapes.PAVING:
            tex = paving_texture()
            ia = (x * np.float32(64 / PAVING_TILE)).astype(np.int32) & 63
            ib = (z * np.float32(64 / PAVING_TILE)).astype(np.int32) & 63
            contrast = np.clip(8.0 / depth[sel], 0.0, 1.0)  # grout lines fade out with distance
            grout = 1.0 - (1.0 - tex[ia, ib]) * contrast
            grain = 1.0 + 0.08 * lookup("fine", x, z, 30.0) * fade[sel]
            base[sel] = base[sel] * (grout * grain)[:, None]
        elif code == shapes.FOLIAGE:
            leaf = lookup("medium", x + z, y, 5.0) + 0.8 * lookup("fine", z - x, y, 14.0)
            leaf += 0.6 * lookup("fine", x - z, y, 40.0) * fade[sel]
            # leaves and gaps at the scale of a pixel or two however far (in real foliage
            # there is always structure at the pixel's size)
            leaf += 0.7 * lookup("fine", x - z, y + 0.5 * x, 1400.0 / depth[sel])
            base[sel] = base[sel] * np.clip(0.75 + 0.4 * leaf, 0.15, 1.7)[:, None]
        elif code == shapes.ROUGH:
            base[sel] = (
                base[sel] * (1.0 + 0.12 * lookup("fine", x + z, y, 40.0) * fade[sel])[:, None]
            )
        elif code == shapes.GLASS:
            base[sel] = _glass(solid.params, x, y, z, base[sel])
        elif code == shapes.CARSIDE:
            base[sel] = _car_side(solid.params, x, y, base[sel])
        elif code == shapes.PHOTO:
            pixel_metres = depth[sel] * np.float32(1.0 / focal)
            base[sel] = _photo(solid.params, x, y, z, pixel_metres, base[sel])
        elif code == shapes.RANDOM:
            albedo = solid.colors[face[sel]]
            base[sel] = _random_pattern(solid.params, x, y, z, albedo, base[sel])
        elif code in (shapes.HEADLIGHTS, shapes.TAILLIGHTS):
            base[sel] = _lamps(solid.params, code, y, z, base[sel])
    return base


def _facade(params, face, x, y, z, base, fade):
    """Windows on a building wall. Texture frame = road frame: x lateral, y down, z along road.

    ``params``: ground y, floor height, window spacing, window width and height
    (fractions of a cell), glass RGB, hash salt, and optionally a shop flag
    (ground-floor shop windows).
    """
    ground_y, floor_h, spacing, win_w, win_h, glass_r, glass_g, glass_b, salt = params[:9]
    # walls facing the road (front/back faces) run along z, end walls along x
    along = np.where(face <= shapes.BACK, z, x)
    height = ground_y - y
    a = along * np.float32(1.0 / spacing)
    b = height * np.float32(1.0 / floor_h)
    col, row = np.floor(a), np.floor(b)
    fa, fh = a - col, b - row
    upper = height > 2.6  # no windows on the ground floor
    inside = (np.abs(fa - 0.5) < win_w / 2) & (np.abs(fh - 0.55) < win_h / 2) & upper
    amp = params[10] if len(params) > 10 else 0.06
    grain = lookup("medium", along, height, 8.0) + 0.5 * lookup("fine", height, along, 30.0)
    stain = lookup("medium", along * 0.2, height * 0.05, 4.0)  # vertical weathering streaks
    out = base * (1.0 + amp * grain * fade + 0.5 * amp * stain)[:, None]
    if len(params) > 11 and params[11] > 0:  # brick courses (7.5 cm), bricks 24 cm long
        course = np.floor(height * np.float32(1 / 0.075))
        bx = np.mod(along * np.float32(1 / 0.24) + 0.5 * np.mod(course, 2), 1.0)
        by = np.mod(height * np.float32(1 / 0.075), 1.0)
        mortar = (np.minimum(bx, 1 - bx) < 0.05) | (np.minimum(by, 1 - by) < 0.1)
        out[mortar] *= np.float32(1.0) - np.float32(0.3) * fade[mortar, None]
        tint = hash01(np.floor(along * np.float32(1 / 0.24)), course, int(salt) + 1)
        out *= (0.85 + 0.3 * tint)[:, None]
    ledge = (np.abs(fh - (0.55 - win_h / 2)) < 0.04 / floor_h) & upper
    out[ledge] *= 0.8
    plinth = height < 0.4
    out[plinth] *= 0.7
    if len(params) > 9 and params[9] > 0:  # shop windows on the ground floor
        shop_a = np.abs(fa - 0.5) < 0.42
        inside |= shop_a & (height > 0.5) & (height < 2.3)
    idx = np.flatnonzero(inside)
    lit = hash01(col[idx], row[idx], int(salt))
    glass = np.array([glass_r, glass_g, glass_b], np.float32) * (0.6 + 0.8 * lit[:, None])
    tint = base[idx] / np.maximum(base[idx].max(axis=1, keepdims=True), 1e-3)
    out[idx] = glass * (0.5 + 0.5 * tint)
    return out


def _photo(params, x, y, z, pixel_metres, base):
    """Foliage or a rough surface with a photograph's detail (:mod:`photo_textures`).

    Texture frame = road frame (x lateral, y down, z along the road). ``params``: texture,
    metres per photograph, contrast, offsets, foliage flag. Foliage keeps the renderer's
    clumps of leaves at the metre scale under the photograph's detail.
    """
    texture, metres, contrast, da, db, foliage = params[:6]
    detail = photo_textures.sample(int(texture), x + z + da, y + db, metres, pixel_metres)
    if foliage:
        clumps = lookup("medium", x + z, y, 5.0)
        gain = np.clip(0.8 + 0.25 * clumps + np.float32(1.6 * contrast) * detail, 0.15, 1.7)
    else:
        gain = np.clip(1.0 + np.float32(contrast) * detail, 0.3, 1.7)
    return base * gain[:, None]


def _random_pattern(params, x, y, z, albedo, base):
    """A domain-randomized surface (:mod:`domain_randomization`; texture frame = road frame).

    ``params``: pattern (0 noise, 1 stripes, 2 checks, 3 spots), period in metres,
    contrast, second colour RGB, direction in the ground plane (radians), hash salt. The
    pattern mixes the face's albedo towards the second colour, keeping its lighting.
    """
    kind, scale, contrast, r, g, b, angle, salt = params[:8]
    inv = np.float32(1.0 / scale)
    u = (x * np.float32(np.cos(angle)) + z * np.float32(np.sin(angle))) * inv
    v = y * inv
    if kind == 0:
        m = 0.5 + 0.3 * (lookup("medium", u, v, 16.0) + 0.5 * lookup("fine", v, u, 32.0))
    elif kind == 1:
        m = 0.5 + 0.5 * np.sin(np.float32(2 * np.pi) * (u + 0.3 * v))
    elif kind == 2:
        m = hash01(np.floor(u), np.floor(v), int(salt))
    else:
        fu, fv = u - np.floor(u) - 0.5, v - np.floor(v) - 0.5
        radius = 0.15 + 0.3 * hash01(np.floor(u), np.floor(v), int(salt))
        m = (fu * fu + fv * fv < radius * radius).astype(np.float32)
    w = (np.float32(contrast) * np.clip(m, 0.0, 1.0)).astype(np.float32)[:, None]
    ratio = np.clip(np.array([r, g, b], np.float32) / np.maximum(albedo, 0.02), 0.0, 4.0)
    return base * (1.0 - w + w * ratio)


def _lamps(params, code, y, z, base):
    """Head/tail lights and a number plate on a car body's end faces (object frame)."""
    nose_y, tail_y, half_w = params[:3]
    top = nose_y if code == shapes.HEADLIGHTS else tail_y
    band = (y > top + 0.03) & (y < top + 0.13)
    side = (np.abs(z) > 0.55 * half_w) & (np.abs(z) < 0.93 * half_w)
    out = base.copy()
    if code == shapes.HEADLIGHTS:
        out[band & side] = (0.85, 0.85, 0.8)
        grille = (y > top + 0.05) & (y < top + 0.16) & (np.abs(z) < 0.4 * half_w)
        out[grille] *= 0.3
    else:
        out[band & side] = (0.7, 0.05, 0.04)
        plate = (y > top + 0.17) & (y < top + 0.28) & (np.abs(z) < 0.28 * half_w)
        out[plate] = (0.85, 0.85, 0.8)
    return out


SKY_REFLECTION = np.array([0.62, 0.7, 0.8], np.float32)


def _glass(params, x, y, z, base):
    """Car windows (object frame): dark glass that mirrors the sky, more so towards the top.

    ``params``: share of the sky reflected, cabin top y and bottom y. A diagonal streak
    pattern along the glass breaks up the reflection like trees and buildings mirrored in it.
    """
    if not params:
        return base + np.float32(0.06) * np.clip(-y - 1.0, 0.0, 1.0)[:, None]
    reflect, top, bottom = params[:3]
    up = np.clip((bottom - y) / max(bottom - top, 1e-3), 0.0, 1.0)  # 0 at the base, 1 at the top
    streak = 0.5 + 0.5 * np.sin(3.0 * (x + z) + 9.0 * y)
    k = (np.float32(reflect) * (0.35 + 0.65 * up) * (0.6 + 0.4 * streak)).astype(np.float32)
    return base * (1.0 - k)[:, None] + SKY_REFLECTION * k[:, None]


def _car_side(params, x, y, base):
    """A car body's side (object frame): dark wheel arches, door seams, a darker sill.

    ``params``: front/rear face tops, half width, front and rear wheel x, wheel radius,
    sill y, belt y, door seam x positions.
    """
    _, _, _, x_front, x_rear, r, sill, belt, door0, door1 = params[:10]
    out = base * (1.0 + 0.18 * np.clip((sill - y) / max(sill - belt, 1e-3), 0.0, 1.0))[:, None]
    rocker = y > sill - 0.22 * (sill - belt)
    out[rocker] *= 0.78
    for xw in (x_front, x_rear):
        arch = (x - xw) ** 2 + (y + r) ** 2 < (1.18 * r) ** 2
        out[arch] = (0.03, 0.03, 0.035)
    upper = y < sill - 0.15 * (sill - belt)
    for xd in (door0, door1):
        out[(np.abs(x - xd) < 0.012) & upper] *= 0.55
    return out
