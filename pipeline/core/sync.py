"""The time offset between a rig's cameras, found from the detections and used.

Convention: the right camera's frame k is exposed δ after the left camera's (δ > 0: the right
camera is late). A moving marker seen by both cameras lies on its epipolar line only when the two
observations are of the same instant, so the epipolar distance of matched detections — with the
right camera's track interpolated in time to the left camera's instants, ``k − δ·fps`` — is
smallest at the true δ (Hartley & Zisserman §9: ``x₂ᵀ F x₁ = 0`` for one instant; motion
across the epipolar lines is what reveals δ, motion along them leaves it unobservable). Both
cameras' tracks are first smoothed alike, by a quadratic least-squares fit over
``2·SMOOTH_HALF + 1`` frames (Savitzky & Golay, *Anal. Chem.* 36(8), 1964): the interpolated right
track then moves with the fitted path, not from one noisy detection to the next (unsmoothed, a
manoeuvring marker that crosses the epipolar lines slowly was found to 0.09–0.28 frame, median per
offset, where the Cramér–Rao bound is 0.10–0.12; 0.05–0.11 smoothed: ``benchmarks/sync.py``).
Smoothing both keeps them consistent: a projection is nearly linear over a few frames, so the
smoothed images are those of the smoothed path (the right track smoothed alone put a fast sine 32
frames off). Each squared distance is divided by its noise variance at its shift (interpolating
between two frames averages their noise), without which the cost dips at every half frame. The
estimate minimises the mean of the weighted, clipped squared epipolar distances over a fine grid of
δ and refines the minimum with a parabola; its 95 % interval comes from a moving-block bootstrap
over frames (blocks keep the residuals' correlation in time), never narrower than the bound the
clip itself gives, widened by ``CI_WIDEN``. Detections missed too often to smooth are used as they
are, with the interval as it was for them; missed so often that few frames have their pairs at every
shift searched, the offset is found coarsely first and finely around it only, and an interval
reaching past that window is not used.

When a clip has ``timestamps.csv`` (per-camera frame times) those times are used instead: the right
camera's detections are interpolated to the left camera's frame times, which handles offsets,
jitter and dropped frames at once.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from functools import partial
from typing import NamedTuple

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.checks import EPIPOLAR_WARN_PX
from pipeline.core.rig import Rig
from pipeline.core.timestamps import align_by_timestamps, median_offset

#: each camera's track is smoothed over this many frames either side before the distances
SMOOTH_HALF = 5
#: … where the smoothed tracks keep this share of the frames with both cameras: with 10 % of the
#: detections missed at random the smoothed tracks kept a tenth of them and erred 0.50 frame (rms)
#: where the detections themselves erred 0.33; with 3 % missed, 0.09 against 0.16
SMOOTH_KEEPS = 0.5
#: the offsets searched finely, in frames either side of zero (fewer for short clips: a quarter of them)
MAX_SHIFT_FRAMES = 10.0
#: beyond that, a coarse search (half-frame steps) out to this many seconds (at most a quarter of the
#: clip) finds larger offsets, then the fine search runs around its best
MAX_SEARCH_S = 2.0
COARSE_STEP = 0.5  # frames
#: markers whose image positions spread less than this (px, 10th to 90th percentile, every camera)
#: are still: the detections hold no information on time
STILL_PX = 5.0
GRID_STEP = 0.02  # frames
#: epipolar distances beyond this (px) count as this: a mismatched pair must not decide δ
CLIP_PX = 6.0
BOOTSTRAP = 200
#: frames per bootstrap block on smoothed tracks: about twice the smoothing's window, over which
#: their distances are correlated (blocks of 10, widened by √2, held 0 in 46 of 48 clean manoeuvring
#: clips; blocks of 20 in 47); on
#: the detections themselves, RAW_BLOCK
BLOCK, RAW_BLOCK = 4 * SMOOTH_HALF, 10
#: the interval is ±1.96 bootstrap standard deviations widened by this: on a marker moving mostly
#: along the epipolar lines the plain bootstrap's interval held 0 in 80–85 % of clean simulated
#: clips; widened by √2 (RAW_CI_WIDEN, the detections themselves) in 48 of 48 clean manoeuvring
#: clips (6 trajectories × 8 noise seeds) and 29 of 30 sine ones. With the smoothed tracks, widened
#: by √2 it held 0 in 47 of the 48, by 1.7 — the least of √2, 1.5, 1.6, 1.7, 1.8 and 2 to do so —
#: in all 48;
#: tests/estimators/test_survive.py::test_clean_clips_keep_zero_in_the_interval measures it
CI_WIDEN, RAW_CI_WIDEN = 1.7, float(np.sqrt(2.0))
MIN_PAIRS = 12
#: where fewer than this share of the frames with both cameras have a pair at every shift of the fine
#: search (a frame needs the right camera's detections over the ±10 frames around it), the offset is
#: found coarsely on the pairs each shift has (:func:`_coarse_offset`), then finely within
#: ±NARROW_SPAN frames of it, where most frames have their pairs. With a quarter of each camera's
#: detections missed at random no clip kept enough frames and none got an offset; narrowed, 78 of 108
#: did, none of the synchronised ones applied (``benchmarks/sync.py``, detections missed at random)
NARROW_KEEPS, NARROW_SPAN = 0.25, 2.0
#: … and its interval widened by this too: the least of 1.1, 1.2 and 1.3 to hold 0 in all 296
#: synchronised clips with detections missed (4 motions × 3 layouts × 10, 25 % of each camera's or 40 %
#: of the frames one camera's, seeds 100–109); without it 2 did not, both of a manoeuvring marker
NARROW_WIDEN = 1.2
#: the distance table is made this many bytes of it at a time (a block of the shifts, every frame):
#: whole, it grows with clip × shifts (48 MB at 3,000 frames, more than the rest of a run grows)
TABLE_BYTES = 4 << 20
#: a table up to this size is made once and kept for both passes over it (which frames have a pair at
#: every shift, then the costs); a larger one is made again for the second
KEPT_TABLE_BYTES = 16 << 20
#: at least this many shifts a block: numpy sums a block's columns over its rows in one order (row
#: after row) however many there are, but one column alone pairwise, which differs in the last bits
MIN_BLOCK_SHIFTS = 32


@dataclass
class SyncEstimate:
    """``offset_s``: δ (s, positive when the right camera is late); ``ci_s``: its 95 % interval;
    ``applied``: whether the estimators used it; ``source``: detections, timestamps, given or off."""

    offset_s: float
    ci_s: tuple[float, float] | None
    applied: bool
    source: str
    residual_px: float | None = None
    note: str = ""

    def as_dict(self) -> dict:
        return asdict(self)

    def describe(self) -> str:
        """One line for the terminal and the report."""
        if self.source == "off":
            return "sync offset: not estimated (--time-offset off)"
        if self.source == "cameras":
            return self.note or "sync offsets: not estimated for more than two cameras"
        if self.source == "timestamps":
            return f"sync offset: from timestamps.csv, median {1000 * self.offset_s:+.2f} ms (right camera late when +)"
        if self.source == "given":
            return f"sync offset: {1000 * self.offset_s:+.2f} ms as given (--time-offset)"
        found = f"sync offset: {1000 * self.offset_s:+.2f} ms"
        if self.ci_s is None:  # none found, or one whose interval reached past the search: not applied
            return f"{found}, not applied ({self.note})" if self.offset_s else f"sync offset: not estimated ({self.note})"
        state = "applied" if self.applied else f"not applied: {self.note or 'the interval contains 0'}"
        return f"{found} (95 % interval {1000 * self.ci_s[0]:+.2f} … {1000 * self.ci_s[1]:+.2f} ms), {state}"


def interpolate_track(uv: np.ndarray, at: np.ndarray) -> np.ndarray:
    """A camera's track (frames × 2, NaN where missed) at fractional frame indices ``at``: linear
    between the two neighbouring frames, NaN where either is missing or outside the clip."""
    n = len(uv)
    lo = np.floor(at).astype(int)
    w = (at - lo)[:, None]
    ok = (lo >= 0) & (lo + 1 < n)
    out = np.full((len(at), 2), np.nan)
    i = lo[ok]
    out[ok] = (1 - w[ok]) * uv[i] + w[ok] * uv[i + 1]
    exact = (w[:, 0] == 0) & (lo >= 0) & (lo < n)  # an integer index needs no right neighbour
    out[exact] = uv[lo[exact]]
    return out


def shift_right(obs: dict[str, np.ndarray], shift_frames: float) -> dict[str, np.ndarray]:
    """Observations with the right camera's track interpolated to the left camera's instants: the
    right camera's frame ``k − shift`` (it is ``shift`` frames late)."""
    out = {}
    for name, Y in obs.items():
        k = np.arange(len(Y), dtype=float)
        out[name] = np.column_stack([Y[:, :2], interpolate_track(Y[:, 2:], k - shift_frames)])
    return out


def savitzky_golay(half: int) -> np.ndarray:
    """The weights that read a quadratic least-squares fit over ``2·half + 1`` frames at its centre
    (Savitzky & Golay 1964); ``[1]`` for ``half`` 0. ``scipy.signal.savgol_coeffs`` gives the same
    (tested), but importing scipy.signal would cost the estimate stage's parent process ~1 s."""
    x = np.arange(-half, half + 1, dtype=float)
    return np.linalg.pinv(np.vander(x, min(3, len(x)), increasing=True))[0]


#: the smoothing's weights, and their sums ``Σ h²`` and ``Σ h_j h_{j+1}`` (a smoothed track's noise
#: variance and its correlation from one frame to the next, in units of the detections' σ²)
_WEIGHTS = savitzky_golay(SMOOTH_HALF)
_SELF, _NEXT = float(_WEIGHTS @ _WEIGHTS), float(_WEIGHTS[:-1] @ _WEIGHTS[1:])


def smooth_track(uv: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """A camera's track (frames × 2) through the smoothing ``weights`` (odd length; default the
    module's); NaN where its window is not whole (the clip's first and last frames, and next to a
    missed detection)."""
    weights = _WEIGHTS if weights is None else weights
    ok = np.all(np.isfinite(uv), axis=1)
    whole = np.convolve(ok.astype(float), np.ones(len(weights)), mode="same") >= len(weights) - 0.5
    filled = np.where(ok[:, None], uv, 0.0)
    out = np.column_stack([np.convolve(filled[:, j], weights[::-1], mode="same") for j in range(uv.shape[1])])
    out[~whole] = np.nan
    return out


def smooth_tracks(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Each marker's observations with both cameras' tracks smoothed (:func:`smooth_track`)."""
    return {name: np.column_stack([smooth_track(Y[:, :2]), smooth_track(Y[:, 2:])]) for name, Y in obs.items()}


def interpolation_variance(shift_frames: float, own: float | None = None, next_: float | None = None) -> float:
    """The noise variance of a squared epipolar distance at a shift, relative to a whole-frame
    shift, for tracks whose samples have variance ``own`` and covariance ``next_`` with the next
    (in σ²; the smoothing's by default): the left point's ``own`` plus the interpolated right one's,
    ``((1 − w)² + w²)·own + 2w(1 − w)·next_`` for the fraction ``w`` of a frame, over ``2·own``. For
    raw detections (1, 0) it is 3/4 at half a frame: left unweighted, the cost dips at every half
    frame and pulls the estimate there."""
    own, next_ = (_SELF if own is None else own), (_NEXT if next_ is None else next_)
    w = float(shift_frames - np.floor(shift_frames))
    return (own + ((1.0 - w) ** 2 + w**2) * own + 2.0 * w * (1.0 - w) * next_) / (2.0 * own)


#: the noise variance at a shift of the detections themselves (unsmoothed)
_RAW = partial(interpolation_variance, own=1.0, next_=0.0)


def _table_blocks(rig: StereoRig, obs: dict[str, np.ndarray], shifts: np.ndarray,
                  variance: Callable[[float], float]) -> Iterator[tuple[slice, np.ndarray]]:
    """:func:`_distance_table` a block of shifts at a time, about :data:`TABLE_BYTES` each: (the block's
    columns, its table). Each column is the whole table's: a column depends on its shift alone."""
    rows = sum(len(Y) for Y in obs.values())
    step = max(MIN_BLOCK_SHIFTS, TABLE_BYTES // (8 * max(rows, 1)))
    for j in range(0, len(shifts), step):
        yield slice(j, j + step), _distance_table(rig, obs, shifts[j : j + step], variance)


def _distance_table(rig: StereoRig, obs: dict[str, np.ndarray], shifts: np.ndarray,
                    variance: Callable[[float], float]) -> np.ndarray:
    """Clipped squared epipolar distances, each over its noise variance at its shift
    (``variance``: :func:`interpolation_variance` for the tracks' kind): (markers·frames) × shifts,
    NaN where no pair exists."""
    rows = []
    for Y in obs.values():
        k = np.arange(len(Y), dtype=float)
        D = np.full((len(Y), len(shifts)), np.nan)
        for j, s in enumerate(shifts):
            right = interpolate_track(Y[:, 2:], k - s)
            d = rig.epipolar_distance(np.column_stack([Y[:, :2], right]))
            D[:, j] = np.minimum(d, CLIP_PX) ** 2 / variance(s)
        rows.append(D)
    return np.vstack(rows)


def _bound(rig: StereoRig, fitted: dict[str, np.ndarray], shift: float, residual: float) -> float:
    """The Cramér–Rao standard deviation (frames) of the shift from the epipolar distances alone
    (Kay, *Estimation Theory*, 1993, ch. 3): each distance, of noise ``residual`` px, moves with the
    shift at the right image's velocity across its epipolar line, read off the fitted right track
    at the shift; the information is the sum over frames of that velocity² over ``residual``².
    A bootstrap over a clip that holds little of the offset can be narrower than this; the
    interval is never."""
    F = rig.fundamental()
    info = 0.0
    for Y in fitted.values():
        k = np.arange(len(Y), dtype=float)
        right = interpolate_track(Y[:, 2:], k - shift)
        velocity = (interpolate_track(Y[:, 2:], k - shift + 0.5) - interpolate_track(Y[:, 2:], k - shift - 0.5))
        line = np.c_[Y[:, :2], np.ones(len(Y))] @ F.T  # the left point's epipolar line in the right image
        normal = line[:, :2] / np.hypot(line[:, 0], line[:, 1])[:, None]
        across = np.sum(normal * velocity, axis=1)
        info += float(np.nansum(np.where(np.isfinite(right).all(axis=1), across, np.nan) ** 2))
    return float(np.sqrt(residual**2 / info)) if info > 0 and residual > 0 else 0.0


class _Tracks(NamedTuple):
    """The tracks the distances are taken on, their noise variance at a shift, and the bootstrap's
    block and widening calibrated for their kind."""

    obs: dict[str, np.ndarray]
    variance: Callable[[float], float]
    block: int
    widen: float


def _fitted(obs: dict[str, np.ndarray]) -> _Tracks:
    """Smoothed tracks (:func:`smooth_tracks`) where they keep :data:`MIN_PAIRS` frames with both
    cameras and at least :data:`SMOOTH_KEEPS` of the detections' pairs, else (a short clip, or
    detections often missed: a window is whole only when all its frames are) the detections
    themselves, as before the smoothing."""
    fitted = smooth_tracks(obs) if SMOOTH_HALF else obs
    if SMOOTH_HALF and _pairs(fitted) >= max(MIN_PAIRS, SMOOTH_KEEPS * _pairs(obs)):
        return _Tracks(fitted, interpolation_variance, BLOCK, CI_WIDEN)
    return _Tracks(obs, _RAW, RAW_BLOCK, RAW_CI_WIDEN)


def _argmin(cost: np.ndarray, shifts: np.ndarray) -> float:
    """The minimum of a sampled cost, refined by the parabola through it and its neighbours."""
    j = int(np.nanargmin(cost))
    if 0 < j < len(cost) - 1 and np.all(np.isfinite(cost[j - 1 : j + 2])):
        a, b, c = cost[j - 1 : j + 2]
        den = a - 2 * b + c
        if den > 0:
            return float(shifts[j] + 0.5 * (a - c) / den * (shifts[1] - shifts[0]))
    return float(shifts[j])


def _image_spread(obs: dict[str, np.ndarray]) -> float:
    """How far the markers move in the images: the largest 10th-to-90th percentile spread of any
    pixel coordinate of any marker (px); noise alone spreads a still marker by about 2.6 σ."""
    spreads = [np.subtract(*np.nanpercentile(Y[np.isfinite(Y).all(axis=1)], [90, 10], axis=0)).max()
               for Y in obs.values() if np.isfinite(Y).all(axis=1).sum() >= 2]
    return float(max(spreads, default=0.0))


def _coarse_offset(rig: StereoRig, obs: dict[str, np.ndarray], wide: float, variance: Callable[[float], float]) -> float:
    """The best shift on a :data:`COARSE_STEP` grid over ±``wide`` frames: the mean clipped distance
    at each shift over the pairs that exist there (at least :data:`MIN_PAIRS`)."""
    shifts = np.arange(-wide, wide + COARSE_STEP / 2, COARSE_STEP)
    cost = np.full(len(shifts), np.nan)
    for cols, D in _table_blocks(rig, obs, shifts, variance):
        have = np.isfinite(D).sum(axis=0)
        with np.errstate(invalid="ignore"):
            cost[cols] = np.where(have >= MIN_PAIRS, np.nansum(D, axis=0) / np.maximum(have, 1), np.nan)
    return float(shifts[int(np.nanargmin(cost))]) if np.isfinite(cost).any() else 0.0


def _pairs(tracks: dict[str, np.ndarray]) -> int:
    """Frames with both cameras' points, over every marker."""
    return sum(int(np.all(np.isfinite(Y), axis=1).sum()) for Y in tracks.values())


def _paired_everywhere(rig: StereoRig, obs: dict[str, np.ndarray], centre: float, span: float,
                       variance: Callable[[float], float]) -> tuple[np.ndarray, np.ndarray, list | None]:
    """The fine grid of shifts within ±``span`` frames of ``centre``, which rows (markers·frames) have a
    pair at every one of them (the cost compares shifts over the same frames), and the distance
    table's blocks when it is small enough to keep (:data:`KEPT_TABLE_BYTES`), else None."""
    shifts = centre + np.arange(-span, span + GRID_STEP / 2, GRID_STEP)
    rows = sum(len(Y) for Y in obs.values())
    once = list(_table_blocks(rig, obs, shifts, variance)) if 8 * rows * len(shifts) <= KEPT_TABLE_BYTES else None
    valid = np.ones(rows, dtype=bool)
    for _, D in once or _table_blocks(rig, obs, shifts, variance):
        valid &= np.all(np.isfinite(D), axis=1)
    return shifts, valid, once


def _only(obs: dict[str, np.ndarray], rows: np.ndarray) -> dict[str, np.ndarray]:
    """The tracks with every frame not in ``rows`` (a mask over the markers' frames, stacked) blanked.
    A search narrowed around the coarse estimate takes the bound over the frames its cost was taken on
    (with a quarter of the detections missed, a fifth of them: the bound over every frame made
    intervals that missed the truth); the full search, whose cost leaves out only the clip's ends,
    over every frame, as ``CI_WIDEN`` was calibrated."""
    out, start = {}, 0
    for name, Y in obs.items():
        keep = rows[start : start + len(Y)]
        out[name], start = np.where(keep[:, None], Y, np.nan), start + len(Y)
    return out


class _Window(NamedTuple):
    """Where the fine search runs: ±``span`` frames around ``centre`` (the coarse search's, out to
    ±``wide``, when it found the offset beyond the fine search or detections are missed often), its
    shifts, the rows with a pair at every one of them, and the kept distance table (or None)."""

    centre: float
    span: float
    wide: float
    shifts: np.ndarray
    valid: np.ndarray
    once: list | None


def _window(rig: StereoRig, obs: dict[str, np.ndarray], n: int, fps: float,
            variance: Callable[[float], float]) -> _Window:
    """The fine search's window (:class:`_Window`) for a clip of ``n`` frames."""
    span = min(MAX_SHIFT_FRAMES, max(1.0, n / 4))
    wide = min(MAX_SEARCH_S * fps, n / 4)
    centre = _coarse_offset(rig, obs, wide, variance) if wide > span else 0.0
    if abs(centre) <= span - 2:  # within the fine search: that search alone, as it was
        centre = 0.0
    else:
        span = NARROW_SPAN
    needed = NARROW_KEEPS * _pairs(obs)  # detections missed often below this (see NARROW_KEEPS)
    narrow = span > NARROW_SPAN and _at_most_paired(obs, span) < needed  # sure without the table
    if not narrow:
        shifts, valid, once = _paired_everywhere(rig, obs, centre, span, variance)
        narrow = span > NARROW_SPAN and valid.sum() < needed
    if narrow:
        centre, span = _coarse_offset(rig, obs, span, variance), NARROW_SPAN
        shifts, valid, once = _paired_everywhere(rig, obs, centre, span, variance)
    return _Window(centre, span, wide, shifts, valid, once)


def _at_most_paired(obs: dict[str, np.ndarray], span: float) -> int:
    """An upper bound on the rows :func:`_paired_everywhere` finds over ±``span`` frames, from which
    detections exist alone: such a row has its left point and the right camera's detections at every
    frame within ``⌈span⌉ − 1`` of it (each is a neighbour of some shift searched). Far below the
    share that narrows the search, it spares building the distance table (half the search's time)."""
    reach = max(int(np.ceil(span)) - 1, 0)
    total = 0
    for Y in obs.values():
        right = np.all(np.isfinite(Y[:, 2:]), axis=1).astype(float)
        whole = np.convolve(right, np.ones(2 * reach + 1), mode="same") >= 2 * reach + 0.5  # none past the ends
        total += int((whole & np.all(np.isfinite(Y[:, :2]), axis=1)).sum())
    return total


def estimate_offset(rig: StereoRig, obs: dict[str, np.ndarray], fps: float, seed: int = 0) -> SyncEstimate:
    """δ from the detections alone (see the module docstring); ``applied`` is left False. It is
    applied (:func:`resolve_sync`) only when the interval excludes 0 and the epipolar residual at δ
    is within the epipolar check's threshold: an offset must explain the mismatch to be one."""
    n = max((len(Y) for Y in obs.values()), default=0)
    if (both := _pairs(obs)) < MIN_PAIRS:
        return SyncEstimate(0.0, None, False, "detections", note=f"only {both} frames with both cameras")
    if (spread := _image_spread(obs)) < STILL_PX:
        return SyncEstimate(0.0, None, False, "detections",
                            note=f"the markers barely move ({spread:.1f} px): the detections hold no information on time")
    raw = obs
    tracks = _fitted(obs)
    obs, variance = tracks.obs, tracks.variance
    w = _window(rig, obs, n, fps, variance)
    centre, span, shifts, valid, once = w.centre, w.span, w.shifts, w.valid, w.once
    n = int(valid.sum())
    if n < MIN_PAIRS:
        return SyncEstimate(0.0, None, False, "detections", note="too few frames with both cameras and their neighbours")
    rng = np.random.default_rng(seed)
    blocks = np.arange(0, n, tracks.block)
    draws = [rng.choice(blocks, size=len(blocks)) for _ in range(BOOTSTRAP)]  # block starts of each resample
    cost, resampled = np.empty(len(shifts)), np.empty((BOOTSTRAP, len(shifts)))
    for cols, D in once or _table_blocks(rig, obs, shifts, variance):
        D = D[valid]
        cost[cols] = D.mean(axis=0)
        for b, starts in enumerate(draws):
            idx = (starts[:, None] + np.arange(tracks.block)).ravel()  # the blocks' rows, block after block
            resampled[b, cols] = D[idx[idx < n]].mean(axis=0)
    best = _argmin(cost, shifts)
    if abs(best - centre) >= span - 2 * GRID_STEP:  # the cost still falls at the edge: no minimum inside the range
        searched = max(w.wide, span)
        return SyncEstimate(0.0, None, False, "detections",
                            note=f"no minimum within ±{searched:g} frames ({searched / fps:.2g} s): an offset larger "
                                 "than that, swapped cameras or mismatched detections?")
    # the detections' own epipolar residual in pixels at δ (unsmoothed, the weight of δ's shift undone)
    residual = float(np.sqrt(np.nanmean(_distance_table(rig, raw, np.array([best]), _RAW)) * _RAW(best)))
    used = _only(obs, valid) if span <= NARROW_SPAN else obs
    spread = max(float(np.std([_argmin(m, shifts) for m in resampled])), _bound(rig, used, best, residual))
    half = tracks.widen * 1.96 * spread * (NARROW_WIDEN if span <= NARROW_SPAN else 1.0)
    if span <= NARROW_SPAN and abs(best - centre) + half > span:  # beyond the window, the costs were not compared
        return SyncEstimate(best / fps, None, False, "detections", residual,
                            note=f"the interval (±{half:.2g} frames) reaches past the ±{span:g} frames searched around "
                                 "the coarse estimate")
    return SyncEstimate(best / fps, ((best - half) / fps, (best + half) / fps), False, "detections", residual)


def resolve_sync(setting: str | float | None, rig: StereoRig, obs: dict[str, np.ndarray], fps: float,
                 timestamps: dict[str, np.ndarray] | None = None) -> tuple[SyncEstimate, dict[str, np.ndarray]]:
    """The offset to use (``--time-offset``: ``auto`` — the default —, ``off`` or seconds) and the
    observations with the right camera aligned to the left camera's instants (for the methods
    that do not model the offset). ``timestamps`` (per camera: frame → time) win over both."""
    if timestamps is not None:
        aligned = align_by_timestamps(obs, timestamps, fps)
        return SyncEstimate(median_offset(timestamps, fps), None, True, "timestamps"), aligned
    if setting in (None, "auto"):
        est = estimate_offset(rig, obs, fps)
        excludes_zero = est.ci_s is not None and not (est.ci_s[0] <= 0.0 <= est.ci_s[1])
        explains = est.residual_px is not None and est.residual_px <= EPIPOLAR_WARN_PX
        est.applied = excludes_zero and explains
        if excludes_zero and not explains:  # the epipolar error is no matter of time (calibration, matching)
            est.note = (f"the epipolar residual at the best offset is {est.residual_px:.1f} px (> {EPIPOLAR_WARN_PX:g}): "
                        "not a time offset")
    elif setting == "off":
        est = SyncEstimate(0.0, None, False, "off")
    else:
        est = SyncEstimate(float(setting), None, float(setting) != 0.0, "given")
    if not est.applied:
        return est, obs
    return est, shift_right(obs, est.offset_s * fps)


# -- more than two cameras -----------------------------------------------------------------------


def _pair_columns(c: int) -> list[int]:
    return [0, 1, 2 * c, 2 * c + 1]


def resolve_view_sync(setting: str | float | None, rig: Rig, obs: dict[str, np.ndarray], fps: float,
                      timestamps: dict[str, np.ndarray] | None = None
                      ) -> tuple[dict[str, SyncEstimate], dict[str, np.ndarray]]:
    """Each camera's offset against the first (N cameras), and the observations with every camera
    aligned to the first camera's instants: per camera, the stereo pair (first, that camera) through
    :func:`resolve_sync` — its timestamps when the clip has them, else found from the detections
    (applied only where significant and explaining the epipolar mismatch), a number of seconds for
    every camera, or off."""
    names = rig.names
    out = {k: v.copy() for k, v in obs.items()}
    found: dict[str, SyncEstimate] = {}
    for c in range(1, rig.n):
        pair = StereoRig(rig.cameras[0], rig.cameras[c], rig.sizes[0])
        sub = {k: v[:, _pair_columns(c)] for k, v in obs.items()}
        ts = {"left": timestamps[names[0]], "right": timestamps[names[c]]} if timestamps is not None else None
        est, aligned = resolve_sync(setting, pair, sub, fps, ts)
        found[names[c]] = est
        for k, v in aligned.items():
            out[k] = _grown(out[k], len(v))
            if ts is not None:  # the first camera placed on the frame grid too (the same for every pair)
                out[k][:, :2] = v[:, :2]
            out[k][:, 2 * c : 2 * c + 2] = v[:, 2:]
    return found, out


def _grown(Y: np.ndarray, n: int) -> np.ndarray:
    """``Y`` padded with NaN rows to ``n`` rows (the frame grid can be longer than a footage)."""
    return Y if len(Y) >= n else np.vstack([Y, np.full((n - len(Y), Y.shape[1]), np.nan)])


def describe_views(found: dict[str, SyncEstimate]) -> str:
    """One line for N cameras' offsets against the first."""
    parts = []
    for name, est in found.items():
        state = ("from timestamps" if est.source == "timestamps" else "applied" if est.applied
                 else "not applied" if est.source == "detections" else est.source)
        parts.append(f"{name} {1000 * est.offset_s:+.2f} ms ({state})")
    return "sync offsets against the first camera: " + ", ".join(parts)
