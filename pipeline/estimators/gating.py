"""What the estimators ask of an observation before they use it: χ² gates on a camera's innovation
and on a triangulation's residual, the robust NIS scale, whether two cameras' detections are one
point, and the reprojection errors every track reports."""

from __future__ import annotations

import math
import statistics
from collections import deque
from dataclasses import dataclass

import numpy as np

from pipeline.core.camera import StereoMeasurementModel, StereoRig
from pipeline.core.chi2 import chi2_upper
from pipeline.core.rig import Rig

#: the smallest detection noise (px) the robust gates assume (see :class:`RobustNISScale`)
GATE_FLOOR_PX = 1.0


def plausible_residual(sigma: float, gate: float) -> float:
    """The χ² gate on a triangulation's summed squared reprojection residual (px²): one degree of
    freedom (the distance from the epipolar line) at probability ``gate``; inf when gating is off."""
    if gate <= 0:
        return float("inf")
    return float(sigma**2 * chi2_upper(1, gate))


def stereo_consistent(model: StereoMeasurementModel, y: np.ndarray, sigma: float, gate: float) -> bool:
    """Whether both cameras' detections of one frame are one point (:func:`views_consistent` with
    both present). A wrong blob in one camera is off the other's epipolar line; two detections far
    from a fixed-gain filter's prediction that agree are its lag (or a real jump, which a restart
    would follow anyway), not an outlier its gate can tell."""
    return bool(np.isfinite(y).all()) and views_consistent(model, y, sigma, gate)


def views_consistent(model: StereoMeasurementModel, y: np.ndarray, sigma: float, gate: float,
                     floor: float = GATE_FLOOR_PX) -> bool:
    """Whether the k ≥ 2 cameras that observe ``y`` see one point: its triangulation lies in front
    of them and reprojects within the χ² gate (2k − 3 degrees of freedom, probability ``gate``) of
    a noise of ``sigma`` px, at least ``floor`` (any residual with gating off, ``gate`` 0)."""
    y = np.asarray(y, dtype=float)[None]
    k = int(np.isfinite(y).reshape(-1, 2).all(axis=1).sum())
    if k < 2:
        return False
    limit = max(sigma, floor) ** 2 * chi2_upper(2 * k - 3, gate) if gate > 0 else float("inf")
    return bool(plausible_triangulation(model, model.inverse_function(y), y, limit)[0])


def plausible_triangulation(model: StereoMeasurementModel, X: np.ndarray, Y: np.ndarray, limit: float) -> np.ndarray:
    """Which triangulations ``X`` (…×3) of ``Y`` (…×2N) are finite, in front of every camera that
    observes them and reproject within ``limit`` px² (:func:`plausible_residual`)."""
    ok = np.all(np.isfinite(X), axis=-1)
    depth = np.where(ok[..., None], model.rig.depths(np.where(ok[..., None], X, 1.0)), -1.0)
    if model.rig.n == 2:
        front = np.all(depth > 0, axis=-1)
    else:
        seen = np.isfinite(Y).reshape(*np.shape(Y)[:-1], model.rig.n, 2).all(axis=-1)
        front = np.all((depth > 0) | ~seen, axis=-1)
    return ok & front & (reprojection_residual(model, X, Y) <= limit)


def camera_gate(gate: float) -> float:
    """The χ² gate on one camera's normalized innovation squared (2 degrees of freedom): the
    quantile ``gate`` of χ²₂ (inf when ``gate`` is 0: no gate). The innovation is normalized by its
    covariance already, so the pixel noise does not enter."""
    if gate <= 0:
        return float("inf")
    return chi2_upper(2, gate)


LN4 = math.log(4.0)  # the median of χ²₂


class RobustNISScale:
    """The gate's scale for filters whose gains ignore their own lag (alpha-beta, ``spsa_stereo``):
    the median of the last ``memory`` NIS values, gated ones included, over χ²₂'s median (ln 4),
    floored at ``(GATE_FLOOR_PX / σ)²`` (at least 1). A lagging filter's innovations grow and widen
    its gate within a few frames; occasional outliers do not move a median. The floor keeps a gate
    from assuming detections more precise than ``GATE_FLOOR_PX``: lossless renders give σ of a few
    hundredths of a pixel, against which a fixed-gain filter's lag of a pixel is hundreds of σ.
    ``value`` is the scale from the innovations added so far (use it, then :meth:`add` the new ones)."""

    def __init__(self, sigma: float = 1.0, memory: int = 30) -> None:
        self.recent: deque = deque(maxlen=memory)
        self.minimum = max(1.0, (GATE_FLOOR_PX / sigma) ** 2)
        self.value = self.minimum

    def add(self, nis) -> None:
        self.recent.extend(float(v) for v in nis if math.isfinite(v))
        if self.recent:
            self.value = max(self.minimum, statistics.median(self.recent) / LN4)


def reprojection_residual(model: StereoMeasurementModel, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Summed squared pixel residual ``‖h(X) − y‖²`` of triangulations ``X`` (…×3) of ``Y`` (…×2N),
    over the cameras that observe them."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r2 = (model.function(np.nan_to_num(X)) - Y) ** 2
        return np.sum(r2, axis=-1) if model.rig.n == 2 else np.nansum(r2, axis=-1)


def camera_nis(model: StereoMeasurementModel, x: np.ndarray, P: np.ndarray, Y: np.ndarray,
               R: np.ndarray | None = None, h: np.ndarray | None = None, H: np.ndarray | None = None,
               S: np.ndarray | None = None) -> np.ndarray:
    """Each camera's normalized innovation squared ``rᵀ S⁻¹ r`` (…×N; NaN where it has no
    observation), ``r = y_c − h_c(x)``, ``S = H_c P H_cᵀ + R_c`` at the predicted state ``x`` (…×d)
    and covariance ``P`` (…×d×d); ``R`` (2N×2N) defaults to the model's ``σ² I``; ``h``, ``H``,
    ``S``: the model at ``x`` and the 2N×2N innovation covariance when the caller has them already."""
    R = model.covar() if R is None else R
    h = model.function(x) if h is None else h
    H = model.jacobian(x) if H is None else H
    if S is None:
        S = H @ P @ np.swapaxes(H, -1, -2) + R  # both cameras at once; each camera's own is its 2×2 block
    if np.ndim(Y) == 1:
        return camera_nis_of(S, Y - h)
    with np.errstate(invalid="ignore"):
        return block_nis(S, Y - h)


def block_nis(S: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Each camera's ``rᵀ S_c⁻¹ r`` over its 2×2 block of ``S`` (…×2N×2N), in closed form, for
    innovations ``r`` (…×2N) → …×N (NaN where a camera has no observation)."""
    n = np.shape(r)[-1] // 2
    out = np.full((*np.shape(r)[:-1], n), np.nan)
    for c in range(n):
        i = 2 * c
        a, b, d = S[..., i, i], S[..., i, i + 1], S[..., i + 1, i + 1]
        u, v = r[..., i], r[..., i + 1]
        out[..., c] = (d * u * u - 2.0 * b * u * v + a * v * v) / (a * d - b * b)  # rᵀ S_c⁻¹ r, 2×2 in closed form
    return out


def camera_nis_of(S: np.ndarray, r: np.ndarray) -> np.ndarray:
    """:func:`camera_nis` of one track from its innovation ``r`` (2N) and its covariance ``S``
    (2N×2N), in Python floats (the same closed form; NaN stays NaN)."""
    s, rr = S.tolist(), r.tolist()
    out = []
    for i in range(0, len(rr), 2):
        u, v = rr[i], rr[i + 1]
        a, b, d = s[i][i], s[i][i + 1], s[i + 1][i + 1]
        out.append((d * u * u - 2.0 * b * u * v + a * v * v) / (a * d - b * b))
    return np.array(out)


def gated_cameras(model: StereoMeasurementModel, x: np.ndarray, P: np.ndarray, Y: np.ndarray,
                  threshold: float, R: np.ndarray | None = None, h: np.ndarray | None = None,
                  H: np.ndarray | None = None, S: np.ndarray | None = None) -> np.ndarray:
    """Which cameras' observations fall outside the χ² gate (…×N booleans), each camera on its own
    (a bad blob in one camera never discards the others'): :func:`camera_nis` above ``threshold``."""
    if not np.isfinite(threshold):
        return np.zeros((*np.shape(Y)[:-1], np.shape(Y)[-1] // 2), dtype=bool)
    with np.errstate(invalid="ignore"):
        return camera_nis(model, x, P, Y, R, h, H, S) > threshold


def reprojection_errors(rig: StereoRig | Rig, positions: np.ndarray, Y: np.ndarray, velocities: np.ndarray | None = None,
                        time_offset: float = 0.0) -> np.ndarray:
    """Per-frame RMS pixel distance between ``h(position)`` and the available observations (with a
    time offset, the right camera sees ``position + velocity·δ``)."""
    ok = np.all(np.isfinite(positions), axis=1)
    r = np.full(Y.shape, np.nan)
    if time_offset and velocities is not None:
        model = StereoMeasurementModel(rig, time_offset=time_offset)
        ok &= np.all(np.isfinite(velocities), axis=1)
        r[ok] = model.function(np.hstack([positions[ok], velocities[ok]])) - Y[ok]
    else:
        r[ok] = rig.project(positions[ok]) - Y[ok]
    with np.errstate(invalid="ignore"):
        n = np.sum(np.isfinite(r), axis=1)
        out = np.sqrt(np.nansum(r**2, axis=1) / np.maximum(n, 1))
    out[n == 0] = np.nan
    return out


#: the probability of the joint check (:func:`joint_gate`): a pair of cameras that each passed its
#: own gate is split only when together they are a one-in-a-million event under the prediction
#: (the stricter the second test, the fewer cameras it drops from a marker that truly manoeuvres)
JOINT_GATE = 1 - 1e-6


@dataclass(frozen=True)
class ViewCheck:
    """What the joint check asks of three cameras or more, from their detections alone (at the
    filter's own noise ``sigma`` and gate probability): see :meth:`odd_one`."""

    model: StereoMeasurementModel
    sigma: float
    gate: float

    def agree(self, y: np.ndarray) -> bool:
        """Whether the cameras of ``y`` see one point (:func:`views_consistent`, no floor)."""
        return views_consistent(self.model, y, self.sigma, self.gate, floor=0.0)

    def odd_one(self, y: np.ndarray) -> int | None:
        """The camera to drop from ``y``: the one without which the others reproject best, if they
        then agree; None when all agree (the prediction is what is off), or when no one camera's
        absence makes the others agree (blobs merged in several views: which is wrong cannot be
        told, and all are kept, as without the check)."""
        if self.agree(y):
            return None
        cams = np.flatnonzero(np.isfinite(y).reshape(-1, 2).all(axis=1))
        Z = np.repeat(np.asarray(y, dtype=float)[None], len(cams), axis=0)
        for i, c in enumerate(cams):
            Z[i, 2 * c : 2 * c + 2] = np.nan
        best = int(np.argmin(reprojection_residual(self.model, self.model.inverse_function(Z), Z)))
        return int(cams[best]) if self.agree(Z[best]) else None


def joint_gate(y: np.ndarray, h: np.ndarray, S: np.ndarray, gate: float, views: ViewCheck | None = None
               ) -> tuple[np.ndarray, int]:
    """(``y`` with cameras dropped, how many) until the cameras kept pass the χ² gate together
    (2·kept degrees of freedom), dropping the one whose own NIS is largest each time. Each camera
    may lie within its own gate while the pair is improbable: a look-alike in one camera shifts
    the disparity, which the prediction's depth uncertainty correlates across the cameras. With
    three cameras or more (``views``) their detections decide which camera goes
    (:meth:`ViewCheck.odd_one`): by the largest own NIS, merged blobs in two views of a ring of
    four had the good cameras dropped and pulled the filters off (EKF 1.12 → 1.77 mm)."""
    dropped = 0
    while True:
        ok = np.isfinite(y)
        if ok.all():  # the common case, without the copies of fancy indexing
            r, Sk = y - h, S
        else:
            rows = np.flatnonzero(ok)
            if len(rows) <= 2:
                return y, dropped
            r, Sk = y[rows] - h[rows], S[np.ix_(rows, rows)]
        if float(r @ np.linalg.solve(Sk, r)) <= chi2_upper(len(r), gate):
            return y, dropped
        worst = _odd_one(y, h, S, views)
        if worst is None:
            return y, dropped
        y = y.copy()
        y[2 * worst : 2 * worst + 2] = np.nan
        dropped += 1


def _odd_one(y: np.ndarray, h: np.ndarray, S: np.ndarray, views: ViewCheck | None) -> int | None:
    """The camera a failed joint check drops (None: none): by the detections with three cameras
    or more (``views``), else the one whose own NIS is largest."""
    if views is not None and np.isfinite(y).sum() >= 6:
        return views.odd_one(y)
    with np.errstate(invalid="ignore"):
        return int(np.nanargmax(camera_nis_of(S, y - h)))


def joint_gate_batch(Y: np.ndarray, h: np.ndarray, S: np.ndarray, gate: float = JOINT_GATE,
                     views: ViewCheck | None = None) -> np.ndarray:
    """:func:`joint_gate` of M tracks at once (``Y``, ``h`` M×2N, ``S`` M×2N×2N): ``Y`` with the
    cameras dropped. The rows a track lacks are set apart (zero residual, unit variance), so each
    track's NIS is over the rows it has."""
    Y = Y.copy()
    kept = np.zeros(len(Y), dtype=bool)  # cameras that agree: as they are
    while True:
        ok = np.isfinite(Y)
        n = ok.sum(axis=1)
        idx = np.flatnonzero((n > 2) & ~kept)
        if not len(idx):
            return Y
        both = ok[idx, :, None] & ok[idx, None, :]
        Sk = np.where(both, S[idx], np.eye(Y.shape[1]))
        r = np.where(ok[idx], Y[idx] - h[idx], 0.0)
        nis = np.einsum("mi,mi->m", r, np.linalg.solve(Sk, r[..., None])[..., 0])
        limit = np.array([chi2_upper(int(d), gate) for d in n[idx]])
        bad = idx[nis > limit]
        if not len(bad):
            return Y
        if views is not None:
            odd = [_odd_one(Y[m], h[m], S[m], views) for m in bad]
            kept[bad] = [c is None for c in odd]
            bad, worst = bad[~kept[bad]], np.array([c for c in odd if c is not None], dtype=int)
        else:
            with np.errstate(invalid="ignore"):
                worst = np.nanargmax(block_nis(S[bad], Y[bad] - h[bad]), axis=1)
        for m, c in zip(bad, worst, strict=True):
            Y[m, 2 * c : 2 * c + 2] = np.nan
