"""A single marker's blob merged with another object of its colour (a look-alike it passes in
front of or behind): the marker's own disc found in the merged blob, so that its centre is not
pulled towards the other object. The blob's centroid lies between the two objects and sits
still while the marker moves; both cameras can then agree on a point that is neither, which no
gate downstream can tell from the marker.

The disc is found where one of the marker's recent size fits inside the blob, nearest the
marker's predicted image position, and its centre and radius are fitted to the blob's boundary
by the algebraic circle fit of Kåsa (*A circle fitting procedure and its error analysis*, IEEE
Trans. Instrum. Meas. 25(1), 1976), on the boundary pixels near that disc's rim only: the arc
the marker shows, not the other object's edges.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from detectors.blob import Detection, MarkerColor
from pipeline.core.lazy import lazy_module

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")

#: a single marker's blob this many times its recent size may be the marker merged with another
#: object of its colour (:func:`unmerge` decides: a marker coming at the camera grows too)
MERGE_GROWTH = 1.05
#: a disc's centre lies where the blob reaches at least this share of the marker's radius all round
FIT_SHARE = 0.8
#: a merged blob's pixels outside the marker's disc hold a lump whose core lies this many px inside
#: its edge (at least twice that across: the look-alike's share, not the disc's own rim), on one
#: side of the disc (their centroid outside it; a tilted plate's ellipse leaves them on two)
LUMP_PX = 1.5
#: boundary pixels within this many px of the disc's rim take part in the circle fit: those within
#: ``INLIER_PX`` of the circle through the most of them, of ``TRIALS`` random triples
RIM_PX, INLIER_PX, TRIALS = 2.5, 0.75, 300
#: the fit is the marker's when its radius is within this factor of the marker's recent radius and
#: its inliers cover at least this share of the circle (in 10° sectors)
RADIUS_FACTOR, MIN_ARC = 1.3, 0.5


def kasa_fit(pts: np.ndarray) -> tuple[float, float, float]:
    """The circle ``(cx, cy, r)`` minimising ``Σ (x² + y² + D x + E y + F)²`` over the points
    (Kåsa 1976): linear least squares, exact for points on a circle."""
    x, y = pts[:, 0], pts[:, 1]
    A = np.column_stack([x, y, np.ones_like(x)])
    (D, E, F), *_ = np.linalg.lstsq(A, -(x * x + y * y), rcond=None)
    cx, cy = -D / 2.0, -E / 2.0
    return float(cx), float(cy), float(np.sqrt(max(cx * cx + cy * cy - F, 0.0)))


def _consensus_arc(edge: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Of the circles through :data:`TRIALS` random triples of ``edge`` points (RANSAC: Fischler &
    Bolles, CACM 24(6), 1981), the one most points lie within :data:`INLIER_PX` of: those points'
    mask, the marker's arc and not the straight edges of what it merged with."""
    tri = edge[rng.integers(0, len(edge), (TRIALS, 3))]
    (ax, ay), (bx, by), (cx, cy) = tri[:, 0].T, tri[:, 1].T, tri[:, 2].T
    den = 2.0 * (ax * (by - cy) + bx * (cy - ay) + cx * (ay - by))
    ok = np.abs(den) > 1e-9
    a2, b2, c2 = ax * ax + ay * ay, bx * bx + by * by, cx * cx + cy * cy
    with np.errstate(divide="ignore", invalid="ignore"):
        ux = (a2 * (by - cy) + b2 * (cy - ay) + c2 * (ay - by)) / den
        uy = (a2 * (cx - bx) + b2 * (ax - cx) + c2 * (bx - ax)) / den
        r = np.hypot(ax - ux, ay - uy)
        dist = np.abs(np.hypot(edge[None, :, 0] - ux[:, None], edge[None, :, 1] - uy[:, None]) - r[:, None])
    votes = np.where(ok, (dist <= INLIER_PX).sum(axis=1), -1)
    return dist[int(np.argmax(votes))] <= INLIER_PX


def disc_in_mask(mask: np.ndarray, radius: float, near: tuple[float, float]) -> tuple[float, float, float] | None:
    """The centre and radius ``(u, v, r)`` (pixels of ``mask``) of the disc of about ``radius``
    that the binary ``mask`` holds nearest ``near``, fitted to the rim it shows; None when no
    disc of that size fits, or its rim does not show as a circle (:data:`RADIUS_FACTOR`,
    :data:`MIN_ARC`)."""
    m = (mask > 0).astype(np.uint8)
    depth = cv2.distanceTransform(np.pad(m, 1), cv2.DIST_L2, 5)[1:-1, 1:-1]
    ys, xs = np.nonzero(depth >= FIT_SHARE * radius)
    if not len(xs):
        return None
    k = int(np.argmin((xs - near[0]) ** 2 + (ys - near[1]) ** 2))
    contours, _ = cv2.findContours(m, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    edge = np.concatenate([cc.reshape(-1, 2) for cc in contours]).astype(float)
    # the disc's centre lies within (1 − FIT_SHARE)·radius of that point: its rim within radius ± that
    edge = edge[np.abs(np.hypot(edge[:, 0] - xs[k], edge[:, 1] - ys[k]) - radius) <= RIM_PX + (1 - FIT_SHARE) * radius]
    if len(edge) < 8:
        return None
    arc = _consensus_arc(edge, np.random.default_rng(0))
    if arc.sum() < 8:
        return None
    u, v, r = kasa_fit(edge[arc])
    sectors = np.unique((np.degrees(np.arctan2(edge[arc, 1] - v, edge[arc, 0] - u)) // 10).astype(int))
    if not (radius / RADIUS_FACTOR <= r + 0.5 <= radius * RADIUS_FACTOR) or len(sectors) < MIN_ARC * 36:
        return None
    return u, v, r + 0.5  # boundary pixels' centres lie half a pixel inside the blob's edge


def unmerge(frame: np.ndarray, mk: MarkerColor, d: Detection, area: float, near: tuple[float, float]) -> Detection | None:
    """``d``, a blob of ``mk`` larger than the marker's recent ``area``, replaced by the marker's
    own disc in it (:func:`disc_in_mask`) nearest ``near`` (its predicted position), reported with
    that disc's area; None when the blob holds no such disc, or nothing beside it but its rim
    (:data:`LUMP_PX`)."""
    half = int(2.0 * np.sqrt(d.area / np.pi)) + 4
    H, W = frame.shape[:2]
    x0, y0 = max(int(d.u) - half, 0), max(int(d.v) - half, 0)
    x1, y1 = min(int(d.u) + half + 1, W), min(int(d.v) + half + 1, H)
    mask = mk.mask(cv2.cvtColor(frame[y0:y1, x0:x1], cv2.COLOR_BGR2HSV))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    if n < 2:
        return None
    blob = labels == 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    disc = disc_in_mask(blob, float(np.sqrt(area / np.pi)), (near[0] - x0, near[1] - y0))
    if disc is None:
        return None
    u, v, r = disc
    yy, xx = np.mgrid[: blob.shape[0], : blob.shape[1]]
    rest = blob & ((xx - u) ** 2 + (yy - v) ** 2 > (r + 0.5) ** 2)  # the blob beyond the disc
    core = cv2.distanceTransform(np.pad(rest.astype(np.uint8), 1), cv2.DIST_L2, 5).max()
    if core < LUMP_PX or np.hypot(xx[rest].mean() - u, yy[rest].mean() - v) <= r:
        return None  # the disc alone, with a ragged rim, or with a rim all round (an ellipse)
    own = int(blob.sum() - rest.sum())  # the blob's pixels in the disc: its size as reported
    return Detection(d.marker, u + x0, v + y0, float(own), d.score)
