"""Colour blob detection with sub-pixel centroids.

Per marker: an HSV range → ``cv2.inRange`` mask → ``cv2.connectedComponentsWithStats`` → size and
roundness filters → the centroid of the component weighted by how much of each pixel the marker
covers (:mod:`detectors.centroid`), which resolves the anti-aliased rim and gives sub-pixel accuracy. An optional
``cv2.SimpleBlobDetector`` backend runs on the same mask.
"""

from __future__ import annotations

import colorsys
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal

import numpy as np

from detectors.centroid import chroma_centre, unmixed_centre
from pipeline.core.errors import StereotrackError
from pipeline.core.lazy import lazy_module

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: --help and `methods` need no OpenCV

@dataclass(frozen=True)
class MarkerColor:
    """A marker's HSV range in OpenCV units (H 0–179, S and V 0–255); ``h_lo > h_hi`` wraps (red).
    ``shaded``: the marker is a lit object (a lit render), whose centre is found by
    unmixing its rim from the background rather than from its chroma (:mod:`detectors.centroid`)."""

    name: str
    h_lo: int
    h_hi: int
    s_min: int = 80
    v_min: int = 60
    shaded: bool = False

    @classmethod
    def from_rgb(cls, name: str, rgb: tuple[int, int, int], hue_tol: int = 10) -> MarkerColor:
        """Range around an RGB colour (as rendered with flat shading)."""
        h, s, v = colorsys.rgb_to_hsv(*(c / 255 for c in rgb))
        hue = round(h * 180) % 180
        return cls(name, (hue - hue_tol) % 180, (hue + hue_tol) % 180, max(40, int(s * 255 * 0.45)), max(40, int(v * 255 * 0.35)))

    @staticmethod
    def parse_window(spec: str) -> tuple[str, tuple[int, int, int, int], int] | None:
        """``NAME@x,y,w,h[@FRAME]`` → (name, window, left frame index, default 0), or None when
        ``spec`` is not a window spec."""
        if "@" not in spec:
            return None
        m = re.fullmatch(r"([\w\-]+)@(-?\d+),(-?\d+),(\d+),(\d+)(?:@(\d+))?", spec.strip())
        if not m:
            raise StereotrackError(f"bad marker spec {spec!r}: a window-learned marker is NAME@x,y,w,h[@FRAME] (pixels)")
        x, y, w, h = (int(g) for g in m.groups()[1:5])
        return m.group(1), (x, y, w, h), int(m.group(6) or 0)

    @classmethod
    def parse(cls, spec: str) -> MarkerColor:
        """``NAME:HLO-HHI[:SMIN[:VMIN]]`` (OpenCV HSV units) or ``NAME=#RRGGBB``."""
        m = re.fullmatch(r"([\w\-]+)=#?([0-9a-fA-F]{6})", spec.strip())
        if m:
            r, g, b = (int(m.group(2)[i : i + 2], 16) for i in (0, 2, 4))
            return cls.from_rgb(m.group(1), (r, g, b))
        m = re.fullmatch(r"([\w\-]+):(\d+)-(\d+)(?::(\d+))?(?::(\d+))?", spec.strip())
        if not m:
            raise StereotrackError(f"bad marker spec {spec!r}: use NAME:HLO-HHI[:SMIN[:VMIN]] or NAME=#RRGGBB")
        lo, hi = int(m.group(2)), int(m.group(3))
        if not (0 <= lo <= 179 and 0 <= hi <= 179):
            raise StereotrackError(f"bad marker spec {spec!r}: hue must lie in 0..179")
        smin, vmin = (int(g) if g is not None else default for g, default in ((m.group(4), 80), (m.group(5), 60)))
        return cls(m.group(1), lo, hi, smin, vmin)

    @classmethod
    def learn(cls, name: str, bgr: np.ndarray, roi: tuple[int, int, int, int], source: str = "",
              force: bool = False) -> MarkerColor:
        """The HSV range of the marker in window ``roi`` (x, y, w, h) of a frame, learned by contrast
        with its surroundings, so that a window drawn loosely (the marker's bounding box, or up to
        1.5× it) does not learn the wall behind it. The window's centre (an ellipse of half its
        size: inside the marker however the window was drawn) and its surround (outside the
        window's inscribed ellipse, out to twice the window) vote in hue–saturation histograms; the
        marker's colours are the bins the centre has at least ``CONTRAST`` times as often as the
        surround (the back-projection idea of Swain & Ballard, *Color indexing*, IJCV 7(1), 1991).
        Skin hues are left out unless the centre is mostly skin. The range spans those pixels'
        hues (2nd–98th percentile around the peak, widened by 3); S and V minima sit above what the
        surround has at those hues, and below nearly all of the marker's own pixels.

        The range is then tried on the whole frame: one that selects far more outside the window
        than inside it (the background, or many objects) is an error telling the user to draw the
        window tighter or give a range, unless ``force``."""
        H, W = bgr.shape[:2]
        x, y, w, h = roi
        if w <= 0 or h <= 0 or x < 0 or y < 0 or x + w > W or y + h > H:
            raise StereotrackError(f"marker window {name}@{x},{y},{w},{h} lies outside the {W}×{H} frame{source}")
        try:
            mk = cls._learn_centre(name, bgr, roi, source)
        except StereotrackError:  # a loose window, the marker off its centre: the compact blob it holds
            blob = compact_blob(bgr, roi)
            if blob is None:
                raise
            mk = cls._learn_centre(name, bgr, blob, source)
        if not force:
            mk._selects_one(bgr, roi, source)
        return mk

    @classmethod
    def _learn_centre(cls, name: str, bgr: np.ndarray, roi: tuple[int, int, int, int], source: str) -> MarkerColor:
        """The range of what the window's centre has and its surround lacks (see :meth:`learn`)."""
        x, y, w, h = roi
        centre, surround = _window_regions(bgr, roi)
        coloured = centre[(centre[:, 1] >= 25) & (centre[:, 2] >= 40)]
        if len(coloured) < max(12, 0.05 * len(centre)):
            raise StereotrackError(f"marker window {name}@{x},{y},{w},{h} holds almost no coloured pixels{source}: "
                                   "put the window on the marker")
        mine = _contrast_pixels(coloured, surround)
        if len(mine) < max(8, 0.1 * len(coloured)):
            raise StereotrackError(f"marker window {name}@{x},{y},{w},{h}: its centre has no colour its surroundings "
                                   f"lack{source}: draw the window around the marker, or give a range NAME:HLO-HHI")
        return cls._range_of(name, mine, surround)

    def _selects_one(self, bgr: np.ndarray, roi: tuple[int, int, int, int], source: str) -> None:
        """Raise when this range selects over ``OUTSIDE_TO_INSIDE`` times as many pixels outside
        the window as inside it, and over 1 % of the frame."""
        x, y, w, h = roi
        mask = self.mask(cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)) > 0
        inside = int(mask[y : y + h, x : x + w].sum())
        outside = int(mask.sum()) - inside
        if outside > OUTSIDE_TO_INSIDE * max(inside, 1) and outside > 0.01 * mask.size:
            raise StereotrackError(
                f"marker window {self.name}@{x},{y},{w},{h}: the colour learned from it ({self.spec()}) selects "
                f"{100 * mask.mean():.0f} % of the frame, {outside / max(inside, 1):.0f}× more outside the window than "
                f"inside{source}: draw the window tighter around the marker, or give a range "
                f"(--markers {self.name}:HLO-HHI:SMIN:VMIN); --force uses it anyway")

    @classmethod
    def _range_of(cls, name: str, mine: np.ndarray, surround: np.ndarray) -> MarkerColor:
        """The range spanning the marker's pixels ``mine`` (N×3 HSV) above the surround's S and V."""
        hist = np.bincount(mine[:, 0], minlength=180).astype(float)
        hist = np.convolve(np.concatenate([hist[-3:], hist, hist[:3]]), np.ones(7), "valid")
        peak = int(np.argmax(hist))
        rel = (mine[:, 0] - peak + 90) % 180 - 90  # hue relative to the peak, wrapped to −90..89
        near = np.abs(rel) <= 25
        lo, hi = np.percentile(rel[near], [2, 98])
        h_lo, h_hi = int(np.floor(peak + lo - 3)) % 180, int(np.ceil(peak + hi + 3)) % 180
        sv = mine[near]
        s_own, v_own = np.percentile(sv[:, 1], [5, 10]), np.percentile(sv[:, 2], [5, 10])
        srel = (surround[:, 0] - peak + 90) % 180 - 90
        same_hue = surround[(srel >= lo - 3) & (srel <= hi + 3)]
        s_min, v_min = 0.7 * s_own[0], 0.7 * v_own[0]
        if len(same_hue) >= 20:  # stay above the surround's pixels of the marker's hues, below most of the marker's
            s_min = max(s_min, min(np.percentile(same_hue[:, 1], 99) + 5, s_own[1]))
        return cls(name, h_lo, h_hi, int(max(25, s_min)), int(max(30, v_min)))

    def display_rgb(self) -> tuple[int, int, int]:
        """The colour this range selects, for drawing: its centre hue at high saturation and value."""
        span = (self.h_hi - self.h_lo) % 180
        hue = (self.h_lo + span / 2) % 180
        r, g, b = colorsys.hsv_to_rgb(hue / 180, 0.85, 0.9)
        return int(r * 255), int(g * 255), int(b * 255)

    def spec(self) -> str:
        """This range as a ``--markers`` spec (``NAME:HLO-HHI:SMIN:VMIN``)."""
        return f"{self.name}:{self.h_lo}-{self.h_hi}:{self.s_min}:{self.v_min}"

    def mask(self, hsv: np.ndarray) -> np.ndarray:
        if self.h_lo <= self.h_hi:
            return cv2.inRange(hsv, (self.h_lo, self.s_min, self.v_min), (self.h_hi, 255, 255))
        a = cv2.inRange(hsv, (self.h_lo, self.s_min, self.v_min), (179, 255, 255))
        b = cv2.inRange(hsv, (0, self.s_min, self.v_min), (self.h_hi, 255, 255))
        return cv2.bitwise_or(a, b)


def occupied(mask: np.ndarray) -> tuple[int, int, int, int]:
    """The bounding box ``(x, y, w, h)`` of a mask's set pixels, its corner moved to even
    coordinates (zeros when none: OpenCV's connected components crash on an empty image).
    Components labelled there are those of the whole mask, with the same label numbers (OpenCV
    labels in 2×2 blocks: an odd shift can reorder them), at a fraction of the cost when the
    colour is rare in the image (a marker, or nothing)."""
    x, y, w, h = cv2.boundingRect(mask)
    if not w:
        return 0, 0, 0, 0
    x0, y0 = x & ~1, y & ~1
    return x0, y0, w + x - x0, h + y - y0


def _components(mask: np.ndarray, labels: bool = True) -> tuple[int, np.ndarray | None, np.ndarray]:
    """``cv2.connectedComponentsWithStats`` (8-connected) of a mask, labelled only inside
    :func:`occupied`'s box: the same count, labels (zeros outside the box; None unless
    ``labels``) and component stats (row 0, the background, aside)."""
    x, y, w, h = occupied(mask)
    if not w:
        return 1, np.zeros(mask.shape, np.uint16) if labels else None, np.zeros((1, 5), np.int32)
    box = mask[y : y + h, x : x + w]
    # 16-bit labels where they cannot overflow: a third of the time of 32-bit ones
    n, inside, stats, _ = cv2.connectedComponentsWithStats(box, connectivity=8,
                                                           ltype=cv2.CV_16U if box.size <= 0xFFFF else cv2.CV_32S)
    stats[:, cv2.CC_STAT_LEFT] += x
    stats[:, cv2.CC_STAT_TOP] += y
    if not labels:
        return n, None, stats
    full = np.zeros(mask.shape, inside.dtype)
    full[y : y + h, x : x + w] = inside
    return n, full, stats


#: a blob elongated up to this ratio (a ball smeared along its motion within one exposure) is
#: still the marker if it fills its ellipse of inertia
MAX_BLUR_ELONGATION = 4.0


def _blurred_roundness(comp: np.ndarray, area: float) -> float:
    """How round a motion-blurred marker is: the share of its ellipse of inertia it fills (1 for a
    filled ellipse of any elongation), or 0 when it is elongated beyond ``MAX_BLUR_ELONGATION``,
    ragged, or not centrally symmetric. A ball smeared along its motion is an ellipse, symmetric
    about its centre; a line is too long, and a ball half hidden behind an edge is a half disc,
    which its own half-turn about its centroid overlaps by well under ``BLUR_SYMMETRY``."""
    c = np.pad(comp.astype(np.uint8), 2)
    m = cv2.moments(c, binaryImage=True)
    if m["m00"] <= 0:
        return 0.0
    cov = np.array([[m["mu20"], m["mu11"]], [m["mu11"], m["mu02"]]]) / m["m00"]
    lo, hi = np.linalg.eigvalsh(cov)
    if lo <= 0 or hi / lo > MAX_BLUR_ELONGATION**2:
        return 0.0
    fill = area / (np.pi * 4.0 * np.sqrt(lo * hi))  # semi-axes 2σ
    cx, cy = m["m10"] / m["m00"], m["m01"] / m["m00"]
    turned = cv2.warpAffine(c, np.array([[-1.0, 0.0, 2 * cx], [0.0, -1.0, 2 * cy]]), c.shape[::-1], flags=cv2.INTER_NEAREST)
    overlap = np.logical_and(c, turned).sum() / max(np.logical_or(c, turned).sum(), 1)
    return float(fill) if fill >= 0.8 and overlap >= BLUR_SYMMETRY else 0.0


#: how much of a blurred blob its half-turn about its centroid must overlap (an ellipse: ~1)
BLUR_SYMMETRY = 0.85


#: a learned range selecting this many times more pixels outside its window than inside is refused
OUTSIDE_TO_INSIDE = 4.0
#: a hue–saturation bin is the marker's when the window's centre has it this many times as often
#: (per pixel) as the window's surround
CONTRAST = 3.0
#: skin: warm hues (OpenCV hue 0–25 of 180) at low to middle saturation, left out of learned ranges
SKIN_HUE, SKIN_S = (0, 25), (30, 170)


def _window_regions(bgr: np.ndarray, roi: tuple[int, int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """HSV pixels (N×3 int) of the window's centre (inside an ellipse of half the window's size)
    and of its surround (outside 1.3× the window's inscribed ellipse, within twice the window)."""
    H, W = bgr.shape[:2]
    x, y, w, h = roi
    cx, cy = x + w / 2.0, y + h / 2.0
    x0, x1 = int(max(0, cx - w)), int(min(W, cx + w))
    y0, y1 = int(max(0, cy - h)), int(min(H, cy + h))
    hsv = cv2.cvtColor(bgr[y0:y1, x0:x1], cv2.COLOR_BGR2HSV).astype(int)
    yy, xx = np.mgrid[y0:y1, x0:x1]
    d = ((xx + 0.5 - cx) / (w / 2.0)) ** 2 + ((yy + 0.5 - cy) / (h / 2.0)) ** 2
    return hsv[d <= 0.25], hsv[d > 1.3**2]  # a guard band: the marker's blurred edge is neither


#: a window's compact blob: saturated this much above the window's median saturation, at least
#: this many pixels, and at least this round (area over its bounding circle's)
BLOB_S_ABOVE, BLOB_MIN_PX, BLOB_ROUND = 30, 12, 0.5


def compact_blob(bgr: np.ndarray, roi: tuple[int, int, int, int]) -> tuple[int, int, int, int] | None:
    """The bounding box (x, y, w, h, in the frame) of the largest compact blob in window ``roi``
    that is more saturated than most of the window: where a loosely drawn window holds its marker
    (off its centre, in a corner), the window to learn from. None when no compact blob stands out."""
    x, y, w, h = roi
    hsv = cv2.cvtColor(bgr[y : y + h, x : x + w], cv2.COLOR_BGR2HSV)
    s, v = hsv[..., 1].astype(int), hsv[..., 2].astype(int)
    mask = ((s > max(np.median(s) + BLOB_S_ABOVE, 60)) & (v > 40)).astype(np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    best = None
    for i in range(1, n):
        bx, by, bw, bh, area = (int(a) for a in stats[i])
        round_ = area / (np.pi * (max(bw, bh) / 2.0) ** 2)
        if area >= BLOB_MIN_PX and round_ >= BLOB_ROUND and (best is None or area > best[4]):
            best = (bx, by, bw, bh, area)
    if best is None:
        return None
    bx, by, bw, bh, _ = best
    return x + bx, y + by, bw, bh


def _contrast_pixels(centre: np.ndarray, surround: np.ndarray) -> np.ndarray:
    """The centre's pixels in hue–saturation bins it has ``CONTRAST`` times as often as the
    surround; skin bins dropped unless skin is most of the centre."""
    def hist(p: np.ndarray) -> np.ndarray:
        return np.histogram2d(p[:, 0], p[:, 1], bins=(30, 8), range=((0, 180), (0, 256)))[0] / max(len(p), 1)

    c, b = hist(centre), hist(surround)
    keep = (c > 0.005) & (c > CONTRAST * b)
    hb, sb = np.minimum(centre[:, 0] // 6, 29), np.minimum(centre[:, 1] // 32, 7)
    mine = centre[keep[hb, sb]]
    skin = (mine[:, 0] >= SKIN_HUE[0]) & (mine[:, 0] <= SKIN_HUE[1]) & (mine[:, 1] >= SKIN_S[0]) & (mine[:, 1] <= SKIN_S[1])
    if skin.mean() < 0.5 if len(mine) else False:
        mine = mine[~skin]
    return mine


@dataclass
class Detection:
    marker: str
    u: float
    v: float
    area: float
    score: float


#: the most blobs of one colour a frame reports (a group of identical markers)
MAX_BLOBS = 256


class BlobDetector:
    """Detect every marker's blobs in a BGR frame. ``max_per_marker`` keeps the best-scoring ones."""

    def __init__(
        self,
        markers: list[MarkerColor],
        min_area: float = 6.0,
        max_area: float = 1e5,
        min_roundness: float = 0.5,
        max_per_marker: int = 1,
        backend: Literal["components", "simpleblob"] = "components",
        coarse: bool = True,
    ) -> None:
        if not markers:
            raise StereotrackError("no markers to detect: give --markers or a clip with scenario.yaml")
        self.markers = markers
        self.min_area, self.max_area, self.min_roundness = min_area, max_area, min_roundness
        self.max_per_marker = max_per_marker
        #: markers whose every blob is reported (a group of identical markers), up to :data:`MAX_BLOBS`
        self.many: frozenset[str] = frozenset()
        self.backend = backend
        self.coarse = coarse  # half-resolution whole-frame search on frames ≥ 640 px wide
        self._small: np.ndarray | None = None
        if backend == "simpleblob":
            p = cv2.SimpleBlobDetector.Params()
            p.filterByColor, p.blobColor = True, 255
            p.filterByArea, p.minArea, p.maxArea = True, min_area, max_area
            p.filterByCircularity, p.minCircularity = True, min_roundness
            p.filterByConvexity = p.filterByInertia = False
            self._sbd = cv2.SimpleBlobDetector.create(p)

    def detect(self, bgr: np.ndarray, hsv: np.ndarray | None = None,
               rois: dict[str, tuple[int, int, int, int]] | None = None,
               expected_area: dict[str, float] | None = None) -> list[Detection]:
        """All detections in one frame (sub-pixel centroids, OpenCV pixel convention).

        ``rois`` (marker → x, y, w, h) restricts a marker's search to a window, typically around
        its previous detection. A marker not found in its window, or found only as a blob much
        smaller than ``expected_area`` (its recent size: a small object of the same colour that
        wandered into the window while the marker left it), is searched in the whole frame and
        the better candidate kept, so windows only save time, never detections.
        """
        full: list[np.ndarray | None] = [hsv]

        def whole() -> np.ndarray:
            converted = full[0]
            if converted is None:
                converted = full[0] = cv2.cvtColor(bgr, cv2.COLOR_BGR2HSV)
            return converted

        out: list[Detection] = []
        for mk in self.markers:
            found: list[Detection] = []
            roi = (rois or {}).get(mk.name)
            if roi is not None and self.backend == "components":
                x, y, w, h = roi
                sub = bgr[y : y + h, x : x + w]
                if sub.size:
                    found = self.detect_marker(mk, sub, cv2.cvtColor(sub, cv2.COLOR_BGR2HSV), x, y)
                expect = (expected_area or {}).get(mk.name)
                if found and expect and found[0].area < 0.4 * expect:
                    windowed = found
                    found = self._detect_coarse(mk, bgr) if self.coarse and bgr.shape[1] >= 640 \
                        else self.detect_marker(mk, bgr, whole(), 0, 0)
                    if not found or windowed[0].score * windowed[0].area >= found[0].score * found[0].area:
                        found = windowed
            if not found:
                if self.coarse and bgr.shape[1] >= 640 and self.backend == "components":
                    found = self._detect_coarse(mk, bgr)
                else:
                    found = self.detect_marker(mk, bgr, whole(), 0, 0)
            out += found[: MAX_BLOBS if mk.name in self.many else self.max_per_marker]
        return out

    def _detect_coarse(self, mk: MarkerColor, bgr: np.ndarray) -> list[Detection]:
        """Whole-frame search at half resolution (every other pixel, so a blob 3 px across or more
        keeps at least one sample), then the full-resolution detection in a window around each
        candidate: about 4× less work per frame, the same centroids."""
        if self._small is None or self._small.shape[:2] != (bgr.shape[0] // 2, bgr.shape[1] // 2):
            self._small = np.empty((bgr.shape[0] // 2, bgr.shape[1] // 2, 3), np.uint8)
        small = cv2.resize(bgr, (bgr.shape[1] // 2, bgr.shape[0] // 2), dst=self._small, interpolation=cv2.INTER_NEAREST)
        mask = mk.mask(cv2.cvtColor(small, cv2.COLOR_BGR2HSV))
        n, _, stats = _components(mask, labels=False)
        found: list[Detection] = []
        H, W = bgr.shape[:2]
        for i in range(1, n):
            x, y, w, h, area = stats[i]
            if 4 * area > self.max_area:
                continue
            x0, y0 = max(2 * x - 6, 0), max(2 * y - 6, 0)
            x1, y1 = min(2 * (x + w) + 6, W), min(2 * (y + h) + 6, H)
            sub = bgr[y0:y1, x0:x1]
            for d in self.detect_marker(mk, sub, cv2.cvtColor(sub, cv2.COLOR_BGR2HSV), x0, y0):
                if not any(abs(d.u - e.u) < 1 and abs(d.v - e.v) < 1 for e in found):
                    found.append(d)
        found.sort(key=lambda d: (-d.score * d.area))
        return found

    def detect_marker(self, mk: MarkerColor, bgr: np.ndarray, hsv: np.ndarray, ox: int = 0, oy: int = 0) -> list[Detection]:
        """One marker's blobs in ``bgr`` (its HSV given), best first; ``ox, oy``: the image's
        offset in the frame (a search window)."""
        mask = mk.mask(hsv)
        if self.backend == "simpleblob":
            found = [Detection(mk.name, kp.pt[0] + ox, kp.pt[1] + oy, np.pi * (kp.size / 2) ** 2, 1.0)
                     for kp in self._sbd.detect(mask)]
            return sorted(found, key=lambda d: -d.area)
        labels, _, blobs = self.blobs(mask, ox, oy)
        found = []
        for i, (x, y, w, h, area), roundness in blobs:
            u, v = self._refine(labels, i, bgr, hsv, x, y, w, h, mk)
            found.append(Detection(mk.name, u + ox, v + oy, float(area), float(min(roundness, 1.0))))
        found.sort(key=lambda d: (-d.score * d.area))
        return found

    def blobs(self, mask: np.ndarray, ox: int = 0, oy: int = 0) -> tuple[np.ndarray, np.ndarray, list[tuple]]:
        """A marker's mask as connected components: (labels, stats, the components that pass the
        area and roundness filters as ``(label, (x, y, w, h, area), roundness)``); ``ox, oy``: the
        mask's offset in the frame (a component cut by a search window's edge is left to the
        whole-frame search)."""
        _, labels, stats = _components(mask)
        assert labels is not None  # asked for
        kept = []
        H, W = mask.shape
        for i, (x, y, w, h, area) in enumerate(stats.tolist()[1:], start=1):  # Python ints: cheaper than numpy's
            if area < self.min_area or area > self.max_area:
                continue
            if ox or oy:  # a blob cut by the window's edge: let the whole-frame search see it whole
                if (x == 0 and ox > 0) or (y == 0 and oy > 0) or x + w >= W or y + h >= H:
                    continue
            roundness = area / (np.pi * (max(w, h) / 2.0) ** 2)
            if roundness < self.min_roundness or min(w, h) < 0.5 * max(w, h):
                roundness = _blurred_roundness(labels[y : y + h, x : x + w] == i, area)
                if roundness < self.min_roundness:
                    continue
            kept.append((i, (x, y, w, h, area), roundness))
        return labels, stats, kept

    @staticmethod
    def _refine(labels, i, bgr, hsv, x, y, w, h, mk: MarkerColor) -> tuple[float, float]:
        """The blob's sub-pixel centre: :func:`~detectors.centroid.unmixed_centre` for a shaded
        marker, else :func:`~detectors.centroid.chroma_centre`."""
        centre = unmixed_centre if mk.shaded else chroma_centre
        return centre(labels, i, bgr, hsv, (x, y, w, h), mk)
