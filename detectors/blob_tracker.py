"""The ``blob`` detector: :class:`~detectors.blob.BlobDetector` per frame, searching first in a
window around each marker's last detection, rejecting a same-coloured blob much smaller (or larger)
than the marker's recent size, and labelling a one-colour four-point target's points consistently."""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Collection

import numpy as np

from detectors.base import Detector, register
from detectors.blob import BlobDetector, Detection, MarkerColor
from detectors.merged import MERGE_GROWTH, unmerge

#: recent blob areas kept per marker (their median is the size a window's find must reach)
AREA_MEMORY = 5
#: a blob this many times smaller or larger than the marker's recent size is not the marker (a ball
#: that left the view is not re-found as a speck of its colour on the wall): at least this many
#: recent sizes make the judgement
SIZE_JUMP = 20.0
SIZE_SAMPLES = 3
#: frames a blob of a marker's colour seen beside it counts as a look-alike nearby (hidden behind the
#: marker, it comes out on the other side)
BESIDE_FRAMES = 30
#: … a blob at least this share of the marker's size (smaller ones: pieces of the marker split by a
#: finger or its own motion blur, on real footage)
LOOKALIKE_SHARE = 0.2


def label_order(points: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """The order (indices into ``points``) that numbers four image points as Soifer, Fursov &
    Kharitonov do: 2 and 4 on the rotation axis (the pair 2R apart, not foreshortened, i.e. the
    longer diagonal), 2 to the right; 1 above the axis. With the previous frame's labelled points,
    keep labels by optimal assignment instead, so labels never swap while the target moves."""
    if previous is not None and np.all(np.isfinite(previous)):
        from scipy.optimize import linear_sum_assignment  # imported here: 0.25 s at start-up

        cost = np.linalg.norm(points[:, None, :] - previous[None, :, :], axis=2)
        rows, cols = linear_sum_assignment(cost)
        order = np.empty(4, dtype=int)
        order[cols] = rows
        return order
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    pairs = [((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))]
    (a, b), (c, e) = max(pairs, key=lambda pr: max(d[pr[0]], d[pr[1]]))
    axis, other = ((a, b), (c, e)) if d[a, b] >= d[c, e] else ((c, e), (a, b))
    p2, p4 = sorted(axis, key=lambda i: -points[i, 0])
    direction = points[p2] - points[p4]
    normal = np.array([direction[1], -direction[0]])  # points "up" (−y) for a rightward axis
    p1, p3 = sorted(other, key=lambda i: -float((points[i] - points[p4]) @ normal))
    return np.array([p1, p2, p3, p4])


def label_four_points(points: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """The four points in label order (see :func:`label_order`)."""
    return points[label_order(points, previous)]


def search_window(d: Detection, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """Search window for the next frame: the blob's size plus room for fast motion."""
    r = max(np.sqrt(d.area / np.pi), 2.0)
    half = int(3 * r + 24)
    x0, y0 = max(int(d.u) - half, 0), max(int(d.v) - half, 0)
    return x0, y0, min(2 * half, shape[1] - x0), min(2 * half, shape[0] - y0)


@register
class BlobTracker(Detector):
    """Blob detection with per-marker search windows and target labelling (one per camera)."""

    name = "blob"
    forks = True
    labels_targets = True
    reports_many = True

    def __init__(self, markers: list[MarkerColor], groups: dict[str, list[str]] | None = None,
                 roi: tuple[int, int, int, int] | None = None, identical: Collection[str] = ()) -> None:
        super().__init__(markers, groups, roi, identical)
        self.blob = BlobDetector(markers, max_per_marker=4)
        self.blob.many = self.identical
        self.grouped = {n for names in self.groups.values() for n in names} | self.identical
        self.windows: dict[str, tuple[int, int, int, int]] = {}
        self.areas: dict[str, deque] = {}
        self.labelled: dict[str, np.ndarray] = {}
        self.colours = {mk.name: mk for mk in markers}
        self.frame = 0  # frames seen: the recent positions' clock
        self.recent: dict[str, deque] = {}  # per single marker: its last two (frame, u, v)
        self.others: dict[str, list[Detection]] = {}  # this frame, per single marker: its colour's other blobs
        self.beside: dict[str, int] = {}  # per single marker: the last frame a blob of its colour lay beside it

    def reset(self) -> None:  # the look-alikes seen stay: a dropped frame does not move them
        self.windows, self.recent = {}, {}

    def detect(self, frame: np.ndarray) -> list[Detection]:
        self.others = {}
        expected = {m: statistics.median(a) for m, a in self.areas.items() if a}
        dets = self._best_per_marker(self.blob.detect(frame, rois=self.windows, expected_area=expected))
        dets = [d if d.marker in self.grouped else self._own_disc(frame, d, expected.get(d.marker))
                for d in dets if d.marker in self.grouped or self._plausible_size(d)]
        self.frame += 1
        for d in dets:
            if d.marker not in self.grouped:
                self.recent.setdefault(d.marker, deque(maxlen=2)).append((self.frame, d.u, d.v))
        self.windows = {d.marker: search_window(d, frame.shape) for d in dets if d.marker not in self.grouped}
        for d in dets:  # a marker not seen keeps its recent sizes: what comes back must match them
            self.areas.setdefault(d.marker, deque(maxlen=AREA_MEMORY)).append(d.area)
        return dets

    def _own_disc(self, frame: np.ndarray, d: Detection, area: float | None) -> Detection:
        """``d``, or where it is :data:`~detectors.merged.MERGE_GROWTH` times the marker's recent
        size and a look-alike lay beside it in the last :data:`BESIDE_FRAMES` frames (perhaps
        hidden behind it since), the marker's own disc in it nearest where its last two positions
        put it now (:func:`~detectors.merged.unmerge`). A marker grown with no look-alike near
        (motion blur, a hand, coming closer) keeps its blob's centre."""
        if area is None or d.area < MERGE_GROWTH * area:
            if any(self._lookalike_beside(d, o) for o in self.others.get(d.marker, ())):
                self.beside[d.marker] = self.frame
            return d
        recent = self.recent.get(d.marker)
        near = self.frame - self.beside.get(d.marker, -BESIDE_FRAMES - 1) <= BESIDE_FRAMES
        if not near or not recent or len(self.areas[d.marker]) < SIZE_SAMPLES:
            return d
        k, u, v = recent[-1]
        if len(recent) == 2:  # a constant image velocity over the frames between
            k0, u0, v0 = recent[0]
            step = (self.frame + 1 - k) / (k - k0)
            u, v = u + (u - u0) * step, v + (v - v0) * step
        return unmerge(frame, self.colours[d.marker], d, area, (u, v)) or d

    @staticmethod
    def _lookalike_beside(d: Detection, o: Detection) -> bool:
        """Whether blob ``o`` of ``d``'s colour is a look-alike beside it: :data:`LOOKALIKE_SHARE`
        of its size or more, their outlines within two of ``d``'s radii (math, not numpy: every
        marker, every frame)."""
        r = math.sqrt(d.area / math.pi)
        return o.area >= LOOKALIKE_SHARE * d.area and math.hypot(o.u - d.u, o.v - d.v) - r - math.sqrt(o.area / math.pi) <= 2 * r

    def _plausible_size(self, d: Detection) -> bool:
        """Whether a single marker's blob is within :data:`SIZE_JUMP`× of its recent size (always,
        before :data:`SIZE_SAMPLES` sizes are known)."""
        recent = self.areas.get(d.marker)
        if not recent or len(recent) < SIZE_SAMPLES:
            return True
        size = statistics.median(recent)
        return size / SIZE_JUMP <= d.area <= size * SIZE_JUMP

    def _best_per_marker(self, dets: list[Detection]) -> list[Detection]:
        """The best blob of each marker; a target's four largest, labelled (none when fewer)."""
        by: dict[str, list[Detection]] = {}
        for d in dets:
            by.setdefault(d.marker, []).append(d)
        out: list[Detection] = []
        for name, ds in by.items():
            if name in self.identical:  # every blob, unlabelled: the association tells them apart
                out += ds
            elif name not in self.groups:
                out.append(ds[0])
                self.others[name] = ds[1:]
            elif len(ds) >= 4:  # fewer than four points: the target is skipped this frame
                ds = sorted(ds, key=lambda d: -d.area)[:4]
                pts = np.array([[d.u, d.v] for d in ds])
                order = label_order(pts, self.labelled.get(name))
                self.labelled[name] = pts[order]
                out += [Detection(point, ds[i].u, ds[i].v, ds[i].area, ds[i].score)
                        for point, i in zip(self.groups[name], order, strict=True)]
        return out
