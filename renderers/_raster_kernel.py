"""The compiled loop of :mod:`renderers.raster` (numba, cached on disk, the GIL released so that
cameras render in threads side by side). Rays are in the camera frame, through (x, y, 1): a hit's
parameter t is its depth."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

SPHERE, CYLINDER, BOX = 0, 1, 2


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _sphere(geo, k, x, y):
    """Nearest t > 0 where the ray meets the sphere (centre geo[k, 0:3], radius geo[k, 3]); inf if none."""
    a = x * x + y * y + 1.0
    b = x * geo[k, 0] + y * geo[k, 1] + geo[k, 2]
    c = geo[k, 0] * geo[k, 0] + geo[k, 1] * geo[k, 1] + geo[k, 2] * geo[k, 2] - geo[k, 3] * geo[k, 3]
    disc = b * b - a * c
    if disc < 0.0:
        return math.inf
    t = (b - math.sqrt(disc)) / a
    return t if t > 0.0 else math.inf


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _cylinder(geo, k, x, y):
    """Nearest t > 0 on the closed cylinder (centre geo[k, 0:3], unit axis geo[k, 3:6], radius
    geo[k, 6], half height geo[k, 7]): its two caps and its wall."""
    nx, ny, nz, r, hh = geo[k, 3], geo[k, 4], geo[k, 5], geo[k, 6], geo[k, 7]
    dn = x * nx + y * ny + nz
    cn = geo[k, 0] * nx + geo[k, 1] * ny + geo[k, 2] * nz
    # across the axis: the ray's direction q and the origin's offset w from the axis
    qx, qy, qz = x - dn * nx, y - dn * ny, 1.0 - dn * nz
    wx, wy, wz = cn * nx - geo[k, 0], cn * ny - geo[k, 1], cn * nz - geo[k, 2]
    a = qx * qx + qy * qy + qz * qz
    b = qx * wx + qy * wy + qz * wz
    c = wx * wx + wy * wy + wz * wz - r * r
    best = math.inf
    if dn != 0.0:  # the caps: the planes n·p = cn ± hh, within the radius
        lo, hi = (cn - hh) / dn, (cn + hh) / dn
        t = min(lo, hi) if min(lo, hi) > 0.0 else max(lo, hi)
        if t > 0.0 and a * t * t + 2.0 * b * t + c <= 0.0:
            best = t
    disc = b * b - a * c
    if a > 0.0 and disc >= 0.0:  # the wall: |t q + w|² = r², between the caps
        t = (-b - math.sqrt(disc)) / a
        if 0.0 < t < best and abs(t * dn - cn) <= hh:
            best = t
    return best


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _box(geo, k, x, y):
    """Nearest t > 0 on the box (centre geo[k, 0:3], camera→box rotation geo[k, 3:12] by rows, half extents
    geo[k, 12:15]): the slab test in the box's frame."""
    near, far = -math.inf, math.inf
    for q in range(3):
        m0, m1, m2 = geo[k, 3 + 3 * q], geo[k, 4 + 3 * q], geo[k, 5 + 3 * q]
        o = -(m0 * geo[k, 0] + m1 * geo[k, 1] + m2 * geo[k, 2])
        d = m0 * x + m1 * y + m2
        e = geo[k, 12 + q]
        if d == 0.0:
            if abs(o) > e:
                return math.inf
            continue
        t1, t2 = (-e - o) / d, (e - o) / d
        if t1 > t2:
            t1, t2 = t2, t1
        near, far = max(near, t1), min(far, t2)
        if near > far:
            return math.inf
    if near > 0.0:
        return near
    return math.inf


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _hit(kind, geo, k, x, y):
    """Where the ray (x, y, 1) first meets solid ``k`` (its row of ``geo`` read in place: a row view
    would count references on every call)."""
    if kind == SPHERE:
        return _sphere(geo, k, x, y)
    if kind == CYLINDER:
        return _cylinder(geo, k, x, y)
    return _box(geo, k, x, y)


#: side of the square tiles (px) a solid's bounds are cut into: a tile only one solid's bounds
#: touch, with all four corners on it, is inside its (convex) outline and drawn without rays
TILE = 8


@njit(cache=True, nogil=True, error_model="numpy", inline="always")
def _nearest(kinds, geo, cand, m, far, x, y):
    """The nearest of the ``m`` solids ``cand`` along the ray (x, y, 1), nearer than ``far`` (the
    background's depth; -1: none)."""
    who = -1
    for i in range(m):
        k = cand[i]
        t = _hit(kinds[k], geo, k, x, y)
        if t < far:
            far, who = t, k
    return who


@njit(cache=True, nogil=True, error_model="numpy")
def draw(img, bg, depth, solids, lens, samples, done):  # pragma: no cover - compiled
    """Draw the solids over ``img`` (uint8, the background already in it): every pixel inside some
    solid's bounds (``boxes``: u0, v0, u1, v1) once, tile by tile (:data:`TILE`); in a tile that
    other bounds touch too, a pixel whose four corners see the same solid (or the background) is
    that colour and any other the mean of ``samples``² samples. ``solids``: (kinds, geo, colors,
    boxes); ``lens``: (fx, fy, cx, cy); ``done`` (zeros, image-sized) marks the pixels drawn."""
    kinds, geo, colors, boxes = solids
    fx, fy, cx, cy = lens
    n = len(kinds)
    cand = np.empty(n, np.int64)
    ids = np.empty((TILE + 1, TILE + 1), np.int64)
    h, w = depth.shape
    for j in range(n):
        for tv in range(boxes[j, 1], boxes[j, 3] + 1, TILE):
            for tu in range(boxes[j, 0], boxes[j, 2] + 1, TILE):
                u1, v1 = min(tu + TILE - 1, boxes[j, 2]), min(tv + TILE - 1, boxes[j, 3])
                m = 0
                for k in range(n):
                    if boxes[k, 0] <= u1 and tu <= boxes[k, 2] and boxes[k, 1] <= v1 and tv <= boxes[k, 3]:
                        cand[m] = k
                        m += 1
                if m == 1 and _inside(kinds[j], geo, j, depth, (tu, tv, u1, v1), lens):
                    _fill(img, done, colors[j], (tu, tv, u1, v1))
                    continue
                for b in range(v1 - tv + 2):  # the tile's pixel corners
                    v = tv + b
                    for a in range(u1 - tu + 2):
                        u = tu + a
                        ids[b, a] = _nearest(kinds, geo, cand, m, depth[min(v, h - 1), min(u, w - 1)],
                                             (u - 0.5 - cx) / fx, (v - 0.5 - cy) / fy)
                for v in range(tv, v1 + 1):
                    for u in range(tu, u1 + 1):
                        if done[v, u]:
                            continue
                        done[v, u] = 1
                        a, b = u - tu, v - tv
                        k = ids[b, a]
                        if samples == 1:
                            k = _nearest(kinds, geo, cand, m, depth[v, u], (u - cx) / fx, (v - cy) / fy)
                        elif ids[b, a + 1] != k or ids[b + 1, a] != k or ids[b + 1, a + 1] != k:
                            _sample(img, bg, depth, solids, lens, cand, m, samples, (u, v))
                            continue
                        if k >= 0:
                            for ch in range(3):
                                img[v, u, ch] = np.uint8(colors[k, ch])


@njit(cache=True, nogil=True, error_model="numpy")
def _inside(kind, geo, j, depth, tile, lens):
    """Whether the rays through the four outer corners of pixels u0..u1 × v0..v1 all meet the
    solid nearer than the background (then, the solid being convex, every ray between them does)."""
    u0, v0, u1, v1 = tile
    fx, fy, cx, cy = lens
    for v in (v0, v1 + 1):
        for u in (u0, u1 + 1):
            if not _hit(kind, geo, j, (u - 0.5 - cx) / fx, (v - 0.5 - cy) / fy) < depth[min(v, v1), min(u, u1)]:
                return False
    return True


@njit(cache=True, nogil=True, error_model="numpy")
def _fill(img, done, color, tile):
    """Pixels u0..u1 × v0..v1 of ``tile`` not drawn yet take ``color``."""
    u0, v0, u1, v1 = tile
    for v in range(v0, v1 + 1):
        for u in range(u0, u1 + 1):
            if not done[v, u]:
                done[v, u] = 1
                for ch in range(3):
                    img[v, u, ch] = np.uint8(color[ch])


@njit(cache=True, nogil=True, error_model="numpy")
def _sample(img, bg, depth, solids, lens, cand, m, samples, pixel):
    """Pixel (u, v) as the mean of a samples × samples grid of rays, each meeting the nearest of the
    ``m`` solids ``cand``."""
    kinds, geo, colors, _ = solids
    fx, fy, cx, cy = lens
    u, v = pixel
    r = g = b = 0.0
    for sy in range(samples):
        y = (v + (sy + 0.5) / samples - 0.5 - cy) / fy
        for sx in range(samples):
            x = (u + (sx + 0.5) / samples - 0.5 - cx) / fx
            who = _nearest(kinds, geo, cand, m, depth[v, u], x, y)
            if who < 0:
                r += bg[v, u, 0]
                g += bg[v, u, 1]
                b += bg[v, u, 2]
            else:
                r += colors[who, 0]
                g += colors[who, 1]
                b += colors[who, 2]
    inv = 1.0 / (samples * samples)
    img[v, u, 0] = np.uint8(math.floor(r * inv + 0.5))
    img[v, u, 1] = np.uint8(math.floor(g * inv + 0.5))
    img[v, u, 2] = np.uint8(math.floor(b * inv + 0.5))
