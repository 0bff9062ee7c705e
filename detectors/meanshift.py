"""Meanshift and CamShift tracking (Comaniciu & Meer, *Mean shift*, IEEE TPAMI 24(5), 2002;
Bradski, *Computer vision face tracking*, Intel Technology Journal, 1998).

A hue histogram of the marker, taken from an initial window (the blob detector's first
detection, or a user ROI), is back-projected onto every frame; ``cv2.meanShift`` (fixed window) or
``cv2.CamShift`` (window adapts to the apparent size — the lecture's (x, y, s) extension) climbs
from the window an alpha-beta filter predicts. When the back-projection mass in the window falls
below ``loss_threshold`` the track is lost and the blob detector re-acquires it. The reported point
is the back-projection centroid inside the final window.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np

from detectors.base import Detector, register
from detectors.blob import BlobDetector, Detection, MarkerColor
from pipeline.core.alphabeta import ABFilter
from pipeline.core.errors import StereotrackError
from pipeline.core.lazy import lazy_module

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: --help and `methods` need no OpenCV

CRITERIA = (2 | 1, 20, 0.1)  # cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT (tested equal)


class MeanShiftTracker:
    """Track one marker through a camera's frames with meanshift or CamShift."""

    def __init__(
        self,
        marker: MarkerColor,
        mode: Literal["meanshift", "camshift"] = "meanshift",
        roi: tuple[int, int, int, int] | None = None,
        loss_threshold: float = 0.15,
        window_scale: float = 1.6,
        ab: tuple[float, float] = (0.7, 0.3),
        model_rate: float = 0.1,
    ) -> None:
        self.model_rate = model_rate
        self.marker, self.mode, self.roi = marker, mode, roi
        self.loss_threshold, self.window_scale, self.ab = loss_threshold, window_scale, ab
        self.blob = BlobDetector([marker], min_roundness=0.3)
        self.hist: np.ndarray | None = None
        self.window: tuple[int, int, int, int] | None = None
        self.filter: ABFilter | None = None
        self.size = 0.0
        self.lost = True

    def _mask(self, hsv: np.ndarray) -> np.ndarray:
        """Pixels saturated and bright enough to carry a trustworthy hue (the lecture's S, V gate),
        within the marker's hue range so that nearby objects (a hand) do not pull the centroid."""
        return self.marker.mask(hsv)

    def _learn(self, hsv: np.ndarray, win: tuple[int, int, int, int], rate: float = 1.0) -> None:
        """(Re)learn the hue histogram from a window; ``rate < 1`` blends it into the current model
        (the usual CamShift model update, so a first glimpse at the frame edge does not fix the
        colour model for good)."""
        x, y, w, h = win
        roi, mask = hsv[y : y + h, x : x + w], self._mask(hsv[y : y + h, x : x + w])
        counts = cv2.calcHist([roi], [0], mask, [36], [0, 180]).ravel()
        hist: np.ndarray = np.convolve(np.r_[counts[-1:], counts, counts[:1]], [0.25, 0.5, 0.25], "valid")
        hist = hist.astype(np.float32).reshape(-1, 1)  # smoothed over neighbouring hue bins (hue is circular)
        if hist.sum() <= 0:
            if self.hist is None:
                raise StereotrackError(f"the initial window {win} holds no pixels of marker '{self.marker.name}'")
            return
        cv2.normalize(hist, hist, 0, 255, cv2.NORM_MINMAX)
        self.hist = hist if self.hist is None or rate >= 1 else cv2.addWeighted(self.hist, 1 - rate, hist, rate, 0)

    def _clip(self, cx: float, cy: float, w: float, h: float, shape) -> tuple[int, int, int, int]:
        H, W = shape[:2]
        w, h = max(round(w), 4), max(round(h), 4)
        x = round(cx - w / 2)
        y = round(cy - h / 2)
        x, y = min(max(x, 0), max(W - w, 0)), min(max(y, 0), max(H - h, 0))
        return x, y, min(w, W), min(h, H)

    def _acquire(self, bgr: np.ndarray, hsv: np.ndarray) -> Detection | None:
        found = self.blob.detect(bgr, hsv)
        if not found:
            return None
        d = found[0]
        r = max(np.sqrt(d.area / np.pi), 3.0) * self.window_scale
        self.window = self._clip(d.u, d.v, 2 * r, 2 * r, bgr.shape)
        self.size = 2 * r
        if self.hist is None:
            self._learn(hsv, self._clip(d.u, d.v, 2 * r / self.window_scale, 2 * r / self.window_scale, bgr.shape))
        self.filter = ABFilter(np.array([d.u, d.v]), 1.0, *self.ab)
        self.lost = False
        return d

    def update(self, bgr: np.ndarray) -> Detection | None:
        """Track into the next frame; None when the marker is lost (and not re-acquired)."""
        hsv = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
        H, W = bgr.shape[:2]
        if self.hist is None and self.roi is not None:
            x, y, w, h = self.roi
            if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > W or y + h > H:
                raise StereotrackError(f"--roi {self.roi} lies outside the {W}×{H} frame")
            self._learn(hsv, self.roi)
            self.window, self.size = self.roi, float(max(w, h))
            self.filter = ABFilter(np.array([x + w / 2, y + h / 2]), 1.0, *self.ab)
            self.lost = False
        if self.lost or self.window is None or self.filter is None:
            d = self._acquire(bgr, hsv)
            if d is None:
                return None
        assert self.window is not None and self.filter is not None and self.hist is not None
        bp = cv2.calcBackProject([hsv], [0], self.hist, [0, 180], 1)
        bp = cv2.bitwise_and(bp, self._mask(hsv))
        pred = self.filter.predict()
        _, _, w, h = self.window
        win = self._clip(pred[0], pred[1], w, h, bgr.shape)
        if self.mode == "camshift":
            rot, found = cv2.CamShift(bp, win, CRITERIA)
            if found[2] <= 0 or found[3] <= 0:
                self.lost = True
                return None
            side = max(rot[1]) * 1.2 if max(rot[1]) > 0 else max(found[2], found[3])
            win = self._clip(found[0] + found[2] / 2, found[1] + found[3] / 2, side, side, bgr.shape)
        else:
            _, found = cv2.meanShift(bp, win, CRITERIA)
            win = (int(found[0]), int(found[1]), int(found[2]), int(found[3]))
        x, y, w, h = win
        sub = bp[y : y + h, x : x + w].astype(np.float32)
        mass = float(sub.sum()) / (255.0 * max(w * h, 1))
        if mass < self.loss_threshold * 0.25 or sub.sum() <= 0:
            self.lost = True
            d = self._acquire(bgr, hsv)  # re-acquire in the same frame when possible
            return d
        u, v, m00 = self._refine(bp, x + w / 2, y + h / 2, w, h)
        self.filter.correct(np.array([u, v]))
        self.window = self._clip(u, v, w, h, bgr.shape)
        if mass > self.loss_threshold:
            self._learn(hsv, self.window, self.model_rate)
        self.size = float(max(w, h))
        return Detection(self.marker.name, float(u), float(v), float(m00 / 255.0), min(1.0, mass))

    def _refine(self, bp: np.ndarray, u: float, v: float, w: int, h: int) -> tuple[float, float, float]:
        """Centroid of the back-projection blob at the track point, in a window 2× the track
        window: the connected region of back-projected pixels nearest the window centre, so other
        pixels of similar hue inside the window (a hand holding the ball) do not pull it."""
        x0, y0, ww, hh = self._clip(u, v, 2.0 * w, 2.0 * h, bp.shape)
        sub = (bp[y0 : y0 + hh, x0 : x0 + ww] > 0).astype(np.uint8)
        n, _labels, stats, cents = cv2.connectedComponentsWithStats(sub, connectivity=8)
        if n <= 1:
            return u, v, 0.0
        cu, cv_ = u - x0, v - y0
        # prefer large regions close to the predicted centre
        def preference(i: int) -> float:
            return stats[i, 4] / (1.0 + np.hypot(cents[i, 0] - cu, cents[i, 1] - cv_) / max(w, 1)) ** 2

        best = max(range(1, n), key=preference)
        return float(x0 + cents[best, 0]), float(y0 + cents[best, 1]), float(stats[best, 4] * 255.0)


@register
class MeanShiftDetector(Detector):
    """Meanshift tracking of each marker (one :class:`MeanShiftTracker` per marker and camera)."""

    name = "meanshift"
    forks = True

    def __init__(self, markers: list[MarkerColor], groups: dict[str, list[str]] | None = None,
                 roi: tuple[int, int, int, int] | None = None) -> None:
        super().__init__(markers, groups, roi)
        mode: Literal["meanshift", "camshift"] = "camshift" if self.name == "camshift" else "meanshift"
        self.trackers = [MeanShiftTracker(m, mode, roi) for m in markers]

    def detect(self, frame: np.ndarray) -> list[Detection]:
        return [d for t in self.trackers if (d := t.update(frame)) is not None]


@register
class CamShiftDetector(MeanShiftDetector):
    """CamShift: meanshift whose window adapts to the marker's apparent size."""

    name = "camshift"
