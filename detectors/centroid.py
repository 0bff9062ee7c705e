"""Sub-pixel blob centres: the centroid of a blob's pixels, each weighted by how much of it the
marker covers. Two coverage models:

- :func:`chroma_centre` (flat-coloured markers, as rendered with flat shading): a pixel's chroma
  (max − min of B, G, R) against the blob's typical chroma. Exact when the marker's colour is
  uniform; on a shaded ball it reads the dark limb as partly covered and pulls the centre toward
  the light (by a median (−0.40, −0.46) px on the rendered ``skin_wall`` clip).
- :func:`unmixed_centre` (lit renders): inside the blob every pixel counts whole;
  on its rim each pixel is unmixed into the marker's colour and the background next to it,
  ``p = α·marker + β·background`` (the linear mixing of an edge pixel, as in alpha matting,
  Smith & Blinn, *Blue screen matting*, SIGGRAPH 1996), and covers ``1 − β``: shading scales α
  only, so a dark limb counts as covered.
"""

from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Protocol

import numpy as np

from pipeline.core.lazy import lazy_module

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")

#: the 5×5 structuring element that grows a blob by 2 px (its anti-aliased rim)
DILATE_2PX = np.ones((5, 5), np.uint8)
#: a shaded blob's rim may reach this far (px) beyond its component (a dark limb below the range's
#: V floor), a layer at a time while a layer is this much covered on average; the background is
#: read from the ring this far out (px)
RIM_MAX, LAYER_MIN, RING = 6, 0.1, (7, 9)
#: an unmixing is trusted where the background differs from the marker's colour by this angle
#: (sin² of it) and is this bright (RGB norm): otherwise the chroma model decides
MIN_SIN2, MIN_BACKGROUND = 0.02, 30.0
#: the share of rim pixels that must be unmixable, else the chroma model is used for the blob
MIN_UNMIXABLE = 0.8


class HueRange(Protocol):
    """What the centre needs of a marker's range (``detectors.blob.MarkerColor``)."""

    @property
    def h_lo(self) -> int: ...
    @property
    def h_hi(self) -> int: ...
    @property
    def s_min(self) -> int: ...
    @property
    def v_min(self) -> int: ...


def _quantile(a: np.ndarray, q: float) -> float:
    """``np.quantile(a, q)`` (its default linear method, the same float), from a partial sort of
    the two values around ``q·(n − 1)``: a tenth of the time on a blob's few hundred pixels."""
    n = a.size
    vi = q * (n - 1)
    lo = int(vi)
    hi = min(lo + 1, n - 1)
    part = np.partition(a, [lo, hi] if hi != lo else lo)
    x0, x1, t = part[lo], part[hi], vi - lo
    return float(x0 + (x1 - x0) * t if t < 0.5 else x1 - (x1 - x0) * (1 - t))  # numpy's lerp, both halves


def _hue_ok(hsv: np.ndarray, mk: HueRange) -> np.ndarray:
    """Pixels whose hue lies in the marker's range widened by 5 (a hand around a ball gets none)."""
    return _hue_table(mk.h_lo, mk.h_hi)[hsv[..., 0]]


@functools.lru_cache(maxsize=64)
def _hue_table(h_lo: int, h_hi: int) -> np.ndarray:
    """Per 8-bit hue value, whether it lies in ``h_lo..h_hi`` widened by 5 (wrapping at 180): one
    look-up per pixel instead of a cast and two comparisons (a blob's patch is a few hundred pixels,
    where each numpy call costs more than its work)."""
    hue = np.arange(256)
    lo, hi = (h_lo - 5) % 180, (h_hi + 5) % 180
    return (hue >= lo) & (hue <= hi) if lo <= hi else (hue >= lo) | (hue <= hi)


def _weighted(wts: np.ndarray, x0: int, y0: int, s: float) -> tuple[float, float]:
    """The centroid of weights ``wts`` (summing to ``s``) placed at ``x0, y0`` in the frame."""
    h, w = wts.shape
    xs, ys = np.arange(x0, x0 + w)[None, :], np.arange(y0, y0 + h)[:, None]  # broadcast: the same products as a grid
    return float((wts * xs).sum() / s), float((wts * ys).sum() / s)


def chroma_centre(labels: np.ndarray, i: int, bgr: np.ndarray, hsv: np.ndarray, box: tuple[int, int, int, int],
                  mk: HueRange) -> tuple[float, float]:
    """Colour-coverage-weighted centroid of component ``i`` (bounding ``box``) dilated by 2 px.

    Weight = how much of a pixel the marker covers, from its chroma between the range's minimum
    chroma (``s_min·v_min/255``) and the blob's typical chroma: 1 inside, fractional on the
    anti-aliased rim (sub-pixel accuracy on rendered markers), capped so texture inside a real
    object does not pull the centroid; pixels whose hue is outside the range (±5) get none.
    ``hsv``: ``bgr`` in OpenCV's 8-bit HSV, whose V is max(B, G, R).
    """
    x, y, w, h = box
    H, W = labels.shape
    x0, y0, x1, y1 = max(x - 3, 0), max(y - 3, 0), min(x + w + 3, W), min(y + h + 3, H)
    comp = labels[y0:y1, x0:x1] == i
    keep = cv2.dilate(comp.view(np.uint8), DILATE_2PX).view(bool)  # 0/1 in, 0/1 out
    keep &= _hue_ok(hsv[y0:y1, x0:x1], mk)
    patch = bgr[y0:y1, x0:x1]
    b, g, r = patch[..., 0], patch[..., 1], patch[..., 2]  # per channel: a reduction over 3 is slow
    c = hsv[y0:y1, x0:x1, 2].astype(np.float32) - np.minimum(np.minimum(b, g), r)  # V is max(B, G, R)
    floor = mk.s_min * mk.v_min / 255.0 * 0.5
    inside = c[comp]
    full = max(_quantile(inside, 0.2) - floor, 1.0) if inside.size else 1.0
    wts = c - floor  # clipped to 0..1 and zeroed outside ``keep`` in place: np.clip and np.where cost more
    wts /= full
    np.maximum(wts, 0.0, out=wts)
    np.minimum(wts, 1.0, out=wts)
    wts *= keep  # ≥ 0: a kept weight times 1 is itself, any other times 0 is +0, as np.where gives
    s = wts.sum()
    if s <= 0:
        ys, xs = np.nonzero(comp)
        return float(xs.mean() + x0), float(ys.mean() + y0)
    return _weighted(wts, x0, y0, s)


def unmixed_centre(labels: np.ndarray, i: int, bgr: np.ndarray, hsv: np.ndarray, box: tuple[int, int, int, int],
                   mk: HueRange) -> tuple[float, float]:
    """Centroid of component ``i`` with its interior (the component eroded by 1 px) counted whole
    and each rim pixel by ``1 − β`` of its unmixing against the marker's median colour and the
    local background (the mean of the ring :data:`RING` px around the blob, near the pixel). The
    rim grows a pixel layer at a time while a layer is on average at least :data:`LAYER_MIN`
    covered (a dark limb below the range's V floor), up to :data:`RIM_MAX` px. Falls back to
    :func:`chroma_centre` where the background cannot be told from the marker by colour direction
    (a dark or same-hued background: there shading and coverage cannot be separated) or the blob
    is too small to have an interior."""
    x, y, w, h = box
    H, W = labels.shape
    m = RING[1] + 1
    x0, y0, x1, y1 = max(x - m, 0), max(y - m, 0), min(x + w + m, W), min(y + h + m, H)
    comp = (labels[y0:y1, x0:x1] == i).astype(np.uint8)
    out = cv2.distanceTransform(1 - comp, cv2.DIST_C, 3)  # px outside the component (0 on it)
    interior = cv2.erode(comp, np.ones((3, 3), np.uint8)).astype(bool)
    ring = ((out >= RING[0]) & (out <= RING[1])).astype(np.float32)
    if interior.sum() < 4 or ring.sum() < 8:
        return chroma_centre(labels, i, bgr, hsv, box, mk)
    patch = bgr[y0:y1, x0:x1].astype(np.float32)
    k = (2 * RING[1] + 1,) * 2
    near = cv2.blur(ring, k)
    background = cv2.blur(patch * ring[..., None], k) / np.maximum(near, 1e-6)[..., None]
    rim = (out <= RIM_MAX) & ~interior & (near > 0)
    marker = np.median(patch[interior], axis=0)
    p, bg = patch[rim], background[rim]
    mm, mb, bb = marker @ marker, bg @ marker, (bg * bg).sum(1)
    det = mm * bb - mb * mb  # the 2×2 normal equations of p ≈ α·marker + β·bg, per pixel
    ok = (det > MIN_SIN2 * mm * bb) & (bb > MIN_BACKGROUND**2)
    if ok.mean() < MIN_UNMIXABLE:
        return chroma_centre(labels, i, bgr, hsv, box, mk)
    beta = (mm * (p * bg).sum(1) - mb * (p @ marker)) / np.where(ok, det, 1.0)
    cover = np.zeros(comp.shape)
    cover[rim] = np.where(ok & _hue_ok(hsv[y0:y1, x0:x1], mk)[rim], np.clip(1.0 - beta, 0.0, 1.0), 0.0)
    reach = 0
    while reach < RIM_MAX:
        layer = cover[out == reach + 1]  # empty where the frame's edge cuts the patch
        if not layer.size or layer.mean() < LAYER_MIN:
            break
        reach += 1
    wts = np.where(interior, 1.0, np.where(out <= reach, cover, 0.0))
    return _weighted(wts, x0, y0, wts.sum())
