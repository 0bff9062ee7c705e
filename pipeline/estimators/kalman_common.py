"""Pieces the Kalman-family point estimators share: config, partial updates, the batched Joseph
update and the batched filter loop (one copy, used by ``kf3d`` and ``ekf``), and the
Rauch–Tung–Striebel backward pass (filterpy's ``rts_smoother``)."""

from __future__ import annotations

import dataclasses
import itertools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
from pydantic import Field

from pipeline.core.camera import StereoMeasurementModel
from pipeline.core.chi2 import chi2_upper
from pipeline.estimators.base import Estimator, EstimatorConfig, Start, Step, Track, transition, use_compiled
from pipeline.estimators.gating import (
    JOINT_GATE,
    ViewCheck,
    camera_gate,
    gated_cameras,
    joint_gate,
    joint_gate_batch,
    reprojection_errors,
)


class KalmanConfig(EstimatorConfig):
    """Noise settings of the Kalman family.

    ``process_noise``: spectral density q (m²/s³) of the white-noise acceleration model.
    ``pixel_sigma``: std (px) of detection noise, ``R = σ² I`` (the pipeline sets it from the data
    unless configured). ``q_scale`` and ``r_scale`` multiply the *assumed* Q and R — the thesis's
    "wrong covariances" experiment (Fig. 12) sets them off by orders of magnitude.
    """

    process_noise: float = Field(0.5, gt=0)
    """spectral density q (m²/s³) of the white-noise acceleration model"""
    pixel_sigma: float = Field(1.0, gt=0)
    """std (px) of detection noise, R = σ² I (the pipeline sets it from the data unless configured)"""
    q_scale: float = Field(1.0, gt=0)
    """multiplies the assumed Q (the thesis's wrong-covariance experiment sets it far off)"""
    r_scale: float = Field(1.0, gt=0)
    """multiplies the assumed R"""


_ALL_ROWS = np.arange(4)
_ALL_ROWS.flags.writeable = False


def available_rows(y: np.ndarray) -> np.ndarray:
    """Indices of the observation rows present (both coordinates of a camera go together)."""
    ok = np.isfinite(y)
    if ok.all():
        return _ALL_ROWS if len(ok) == 4 else np.arange(len(ok))
    ok = np.repeat(ok.reshape(-1, 2).all(axis=1), 2)
    return np.flatnonzero(ok)


def joseph_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, r: np.ndarray, R: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of M states at once (filterpy's equations, Joseph form)::

        S = H P Hᵀ + R,  K = P Hᵀ S⁻¹,  x ← x + K r,  P ← (I − K H) P (I − K H)ᵀ + K R Kᵀ

    ``x`` M×d, ``P`` M×d×d, ``H`` M×m×d, residual ``r`` M×m, ``R`` M×m×m.
    """
    PHt = P @ H.transpose(0, 2, 1)
    S = H @ PHt + R
    K = np.linalg.solve(S, PHt.transpose(0, 2, 1)).transpose(0, 2, 1)  # P Hᵀ S⁻¹ (S symmetric)
    x = x + np.einsum("mij,mj->mi", K, r)
    IKH = np.eye(x.shape[1]) - K @ H
    return x, IKH @ P @ IKH.transpose(0, 2, 1) + K @ R @ K.transpose(0, 2, 1)


#: (states M×6, observations M×2N) → (H M×m×6, residual M×m, R M×m×m, has-measurement M)
Linearize = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]


class GatedFilter(Estimator):
    """Per-camera χ² gating and restarts for the Kalman-family filters (mixed into each): a gated
    camera's observation is dropped (set missing) before the ordinary update, so every path —
    :meth:`step`, :meth:`run`, :func:`kalman_batch` — gates identically."""

    config: KalmanConfig  # the host estimator's settings
    #: whether the cameras each gate keeps are checked together
    #: (:func:`~pipeline.estimators.gating.joint_gate`)
    joint_check: bool = False
    #: the host's state transition and process noise (set by its ``reset``)
    A: np.ndarray
    Q: np.ndarray

    def view_check(self) -> ViewCheck | None:
        """What the joint check asks of three cameras or more (None on a stereo pair, where a
        look-alike on the epipolar line makes one point too)."""
        return ViewCheck(self.model, self.model.pixel_sigma, self.config.gate) if self.rig.n >= 3 else None

    def complete(self, track: Track, Y: np.ndarray) -> Track:
        """The filter's track as it is; remembered for its smoother under :func:`filter_passes_shared`."""
        if _PASSES.tracks is not None:
            _PASSES.tracks[_pass_key(self, self.name, Y)] = _copy_track(track, track.method)
        return track

    def gate_threshold(self) -> float:
        cfg = self.config
        if getattr(self, "_gate_key", None) != cfg.gate:  # a χ² quantile costs more than a filter step
            self._gate_key, self._gate_value = cfg.gate, camera_gate(cfg.gate)
        return self._gate_value

    def gate_covariance(self) -> np.ndarray:
        """The pixel noise the gate assumes: the model's ``σ² I``, times ``r_scale`` (read-only;
        made once per noise setting, not every frame)."""
        key = (self.model.pixel_sigma, self.config.r_scale)
        if getattr(self, "_gate_cov_key", None) != key:
            self._gate_cov_key, self._gate_cov = key, self.model.covar() * self.config.r_scale
            self._gate_cov.flags.writeable = False
        return self._gate_cov

    def gate(self, y: np.ndarray, x: np.ndarray, P: np.ndarray, h: np.ndarray | None = None,
             H: np.ndarray | None = None, S: np.ndarray | None = None) -> tuple[np.ndarray, int, Start | None]:
        """(the observation with gated cameras missing, how many were gated, a restart or None):
        each camera on its own, then (``joint_check``) the cameras kept together; a camera the joint
        check drops counts as gated. After ``restart_after`` frames in a row with a camera gated,
        the track restarts from this frame's detections (when they triangulate plausibly). ``h``, ``H``, ``S``: the model at
        ``x`` and the innovation covariance under the gate's noise, when the caller has them."""
        if self.joint_check and (h is None or S is None):
            h, H = self.model.linearize(x)
            S = H @ P @ H.T + self.gate_covariance()
        g = gated_cameras(self.model, x, P, y, self.gate_threshold(), self.gate_covariance(), h, H, S)
        kept = y
        if g.any():
            kept = y.copy()
            for c in np.flatnonzero(g):
                kept[2 * c : 2 * c + 2] = np.nan
        if self.joint_check and self.config.gate > 0:
            assert h is not None and S is not None  # computed above when not given
            kept, dropped = joint_gate(kept, h, S, JOINT_GATE, self.view_check())
            if dropped:
                g = np.isfinite(y).reshape(-1, 2).all(axis=1) & ~np.isfinite(kept).reshape(-1, 2).all(axis=1)
        gated = bool(g.any())
        seen = np.isfinite(y).reshape(-1, 2).any(axis=1).tolist()  # per camera; one track: plain Python
        had = gated or any(seen)
        self.gated_run = self.gated_run + 1 if gated else (0 if had else self.gated_run)
        self.gated_run, self.unseen, self.returning = after_gap(
            self.gated_run, self.unseen, self.returning, seen, gated, self.config.restart_after)
        restart = None
        if self.gated_run >= self.config.restart_after and (gated or drifted(self.model, x, y, self.config.gate)):
            restart = self.initiator.restart(self.frame, self.recent_observations())
            if restart is not None:
                self.gated_run = 0
        return kept, int(g.sum()), restart


def drifted(model: StereoMeasurementModel, x: np.ndarray, y: np.ndarray, gate: float) -> bool:
    """Whether the prediction ``x`` lies outside the χ²₃ gate (probability ``gate``) of this frame's
    triangulation under the triangulation's own covariance: a camera back from a one-camera
    stretch passes its gate however far the depth drifted (the prediction's uncertainty grew with
    it), so the restart it asks for is taken only when the drift is more than the triangulation's
    noise (a short stretch's small drift is left to the update)."""
    X = model.inverse_function(np.asarray(y, dtype=float)[None])[0]
    if gate <= 0 or not np.all(np.isfinite(X)):
        return False
    d = np.asarray(x, dtype=float)[:3] - X
    return float(d @ np.linalg.solve(model.inverse_covariance(X[None])[0], d)) > chi2_upper(3, gate)


def update_gated_run(run, y: np.ndarray, kept: np.ndarray):
    """Frames in a row in which a camera was gated (frames without observations leave the count
    as it is; works on one track or M tracks). Eight in a row do not come from occasional
    outliers (5 % of frames: 0.05⁸); they come from a track that has lost its marker."""
    had = np.any(np.isfinite(y), axis=-1)
    gated = np.any(np.isfinite(y) & ~np.isfinite(kept), axis=-1)
    return np.where(gated, run + 1, np.where(had, 0, run))


def after_gap(run, unseen, returning, had, gated, restart_after: int):
    """A camera back from ``restart_after`` frames or more without an observation restarts the
    track: after a gap of every camera, at its first gated frame within its first ``restart_after``
    observed frames (the prediction is far from the returning marker by the gap's length, not
    because of an outlier); after a one-camera stretch (another camera kept observing), at once,
    when the returning pair triangulates plausibly: the depth drifted along the kept camera's ray,
    and its uncertainty grew so large that the gate lets the returning camera in while an update
    linearised that far off does not bring the depth back. ``had`` and ``unseen`` are per camera
    (…×N: whether it observed this frame; frames since it last did). One track in Python scalars
    and lists, or M tracks as arrays. Returns (gated run, frames unseen per camera, returning
    frames left)."""
    if np.ndim(run) == 0:
        back = any(h and u >= restart_after for h, u in zip(had, unseen, strict=True))
        kept = any(h and u < restart_after for h, u in zip(had, unseen, strict=True))
        returning = restart_after if back else returning
        run = max(run, restart_after) if (gated and returning > 0) or (back and kept) else run
        returning = max(returning - 1, 0) if any(had) else returning
        return int(run), [0 if h else u + 1 for h, u in zip(had, unseen, strict=True)], int(returning)
    back = np.any(had & (unseen >= restart_after), axis=-1)
    kept = np.any(had & (unseen < restart_after), axis=-1)
    returning = np.where(back, restart_after, returning)
    run = np.where((gated & (returning > 0)) | (back & kept), np.maximum(run, restart_after), run)
    returning = np.where(np.any(had, axis=-1), np.maximum(returning - 1, 0), returning)
    return run, np.where(had, 0, unseen + 1), returning


def gated_step(step: Step, n_gated: int, restarted: bool = False) -> Step:
    """A filter's step with its gating recorded (``extra``: cameras gated, restart)."""
    step.extra.update(gated=float(n_gated), restart=float(restarted))
    return step


def kalman_batch(est: GatedFilter, Y: np.ndarray, linearize: Linearize) -> np.ndarray:
    """The filter of a Kalman-family estimator over M tracks at once (M × frames × 4 → M × frames
    × 3): each track starts where :class:`~pipeline.estimators.base.Initiator` says (the same
    start as :meth:`Estimator.run`), then predict with ``est.A, est.Q``, gate each camera as
    :class:`GatedFilter` does (restarting tracks gated too long), and update through
    ``linearize`` on every later frame with a measurement."""
    M, n, _ = Y.shape
    est.reset()
    starts = est.initiator.first_batch(Y)
    begin = np.array([s.frame if s is not None else n for s in starts])
    x, P = np.zeros((M, 6)), np.tile(np.eye(6), (M, 1, 1))
    out = np.full((M, n, 3), np.nan)
    A, Q = est.A, est.Q
    threshold, Rg = est.gate_threshold(), est.gate_covariance()
    run_gated = np.zeros(M, dtype=int)
    unseen, returning = np.zeros((M, Y.shape[2] // 2), dtype=int), np.zeros(M, dtype=int)  # see after_gap
    for k in range(n):
        run = begin < k
        x[run] = x[run] @ A.T
        P[run] = A @ P[run] @ A.T + Q
        for m in np.flatnonzero(begin == k):
            s = starts[m]
            assert s is not None  # a track begins where its start is
            x[m], P[m] = s.state, s.covariance
        idx = np.flatnonzero(run)
        if len(idx):
            Yk = _gate_batch(est, x[idx], P[idx], Y[idx, k], threshold, Rg)
            run_gated[idx] = update_gated_run(run_gated[idx], Y[idx, k], Yk)
            had = np.isfinite(Y[idx, k]).reshape(len(idx), -1, 2).any(axis=2)  # per camera
            gated = np.any(np.isfinite(Y[idx, k]) & ~np.isfinite(Yk), axis=1)
            run_gated[idx], unseen[idx], returning[idx] = after_gap(run_gated[idx], unseen[idx], returning[idx], had,
                                                                   gated, est.config.restart_after)
            fresh = _restart_batch(est, idx, k, Y, run_gated, x, P, gated)
            H, r, R, have = linearize(x[idx], Yk)
            have &= ~fresh
            u = idx[have]
            if len(u):
                x[u], P[u] = joseph_update(x[u], P[u], H[have], r[have], R[have])
        out[begin <= k, k] = x[begin <= k, :3]
    return out


def _gate_batch(est: GatedFilter, x: np.ndarray, P: np.ndarray, Yk: np.ndarray, threshold: float,
                R: np.ndarray) -> np.ndarray:
    """The cameras of M tracks as :meth:`GatedFilter.gate` keeps them (each on its own, then,
    where the filter asks for it, together)."""
    h = H = S = None
    if est.joint_check:
        h, H = est.model.function(x), est.model.jacobian(x)
        S = H @ P @ H.transpose(0, 2, 1) + R
    g = gated_cameras(est.model, x, P, Yk, threshold, R, h, H, S)
    Yk = Yk.copy()
    for c in range(g.shape[1]):
        Yk[g[:, c], 2 * c : 2 * c + 2] = np.nan
    if h is not None and S is not None and np.isfinite(threshold):  # the filter asks for the joint check
        Yk = joint_gate_batch(Yk, h, S, views=est.view_check())
    return Yk


def _restart_batch(est: GatedFilter, idx: np.ndarray, k: int, Y: np.ndarray, run_gated: np.ndarray, x: np.ndarray,
                   P: np.ndarray, gated: np.ndarray) -> np.ndarray:
    """Restart the tracks of ``idx`` gated too long, or back from a one-camera stretch and
    :func:`drifted` (``gated``: which of them were gated this frame); which of them restarted."""
    fresh = np.zeros(len(idx), dtype=bool)
    for i in np.flatnonzero(run_gated[idx] >= est.config.restart_after):
        m = idx[i]
        if not gated[i] and not drifted(est.model, x[m], Y[m, k], est.config.gate):
            continue
        s = est.initiator.restart(k, Y[m, max(0, k + 1 - est.config.restart_after) : k + 1])
        if s is not None:
            x[m], P[m] = s.state, s.covariance
            run_gated[m] = 0
            fresh[i] = True
    return fresh


def rts_smooth(est: GatedFilter, track: Track) -> Track:
    """Rauch–Tung–Striebel backward pass over a filtered track (filterpy's ``rts_smoother`` with
    the filter's constant ``A``, ``Q``), from its first estimate to its last::

        P⁻ₖ₊₁ = A Pₖ Aᵀ + Q,  Cₖ = Pₖ Aᵀ (P⁻ₖ₊₁)⁻¹,
        x̂ₖ ← xₖ + Cₖ (x̂ₖ₊₁ − A xₖ),  P̂ₖ ← Pₖ + Cₖ (P̂ₖ₊₁ − P⁻ₖ₊₁) Cₖᵀ

    Each segment between restarts is smoothed on its own: a restart is a new start, not an update
    of the state before it, so the backward pass must not carry it across."""
    ok = np.flatnonzero(np.all(np.isfinite(track.position), axis=1))
    if len(ok) < 2 or track.covariance is None:  # never started: nothing to smooth
        return track
    smoother = _smoother(est, len(track.position))
    track.position = track.position.copy()
    track.velocity = track.velocity.copy()
    track.covariance = track.covariance.copy()
    restarts = np.flatnonzero(np.nan_to_num(track.extra.get("restart", np.zeros(len(track.position)))) > 0)
    cuts = [ok[0], *[int(r) for r in restarts if r > ok[0]], len(track.position)]
    for a, b in itertools.pairwise(cuts):
        if b - a < 2:
            continue
        xs, Ps = smoother(np.hstack([track.position[a:b], track.velocity[a:b]]), track.covariance[a:b].copy())
        track.position[a:b], track.velocity[a:b], track.covariance[a:b] = xs[:, :3], xs[:, 3:], Ps
    return track


def _smoother(est: GatedFilter, frames: int) -> Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """The backward pass for this filter: the compiled :func:`kernels.rts_backward` for the
    constant-velocity transition every built-in filter uses (tested equal to filterpy's) where
    compiling pays (:func:`~pipeline.estimators.base.use_compiled`), else the numpy one (filterpy's ``rts_smoother``)."""
    if est.A.shape == (6, 6) and np.array_equal(est.A, transition(est.dt)) and use_compiled(frames):
        import pipeline.estimators.compiled as kernels

        def compiled(xs: np.ndarray, Ps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            kernels.rts_backward(xs, Ps, est.dt, np.ascontiguousarray(est.Q, dtype=float))
            return xs, Ps

        return compiled
    from pipeline.estimators.filters import KalmanFilter

    kf = KalmanFilter(dim_x=len(est.A), dim_z=1)
    kf.F, kf.Q = est.A, est.Q
    return kf.rts_smoother


def filtered_step(x: np.ndarray, P: np.ndarray, predicted: bool, f=None, innovation: np.ndarray | None = None,
                  innovation_covariance: np.ndarray | None = None) -> Step:
    """A Kalman-family step from the filter's state; the update's innovation ``y`` and covariance
    ``S`` (from ``f``, a filter that just updated, or given) are kept for NIS."""
    x = np.ravel(x)
    if f is not None:
        innovation, innovation_covariance = np.ravel(f.y), np.array(f.S, dtype=float)
    if innovation is None or predicted:
        return Step(x[:3].copy(), x[3:].copy(), predicted, P.copy())
    return Step(x[:3].copy(), x[3:].copy(), predicted, P.copy(), np.array(innovation, dtype=float).copy(),
                np.array(innovation_covariance, dtype=float).copy())


class _Passes(threading.local):
    """Per thread (a Dask worker runs clips in threads): the filters' finished tracks while
    :func:`filter_passes_shared` is in force, by (filter, settings, observations); None outside it."""

    tracks: dict[tuple, Track] | None = None


_PASSES = _Passes()


@contextmanager
def filter_passes_shared() -> Iterator[None]:
    """Within: each Kalman filter's finished track is remembered, so that its smoother run on the
    same observations with the same settings (``kf3d`` then ``kf3d_rts``) smooths it instead of
    filtering them again: the forward pass is the same computation (the same numbers, tested)."""
    before, _PASSES.tracks = _PASSES.tracks, {}
    try:
        yield
    finally:
        _PASSES.tracks = before


def _pass_key(est: GatedFilter, name: str, Y: np.ndarray) -> tuple:
    """What makes two runs' forward passes the same: the filter, its settings, the rig, the step
    and time offset, the observations."""
    return (name, est.config.model_dump_json(), id(est.rig), est.dt, est.model.time_offset,
            np.ascontiguousarray(Y, dtype=float).tobytes())


def _copy_track(track: Track, method: str) -> Track:
    """A track with its own arrays (callers mask theirs in place), named ``method``."""
    def own(a):
        return None if a is None else np.array(a, copy=True)

    return dataclasses.replace(track, method=method, position=own(track.position), velocity=own(track.velocity),
                               reprojection_error=own(track.reprojection_error), predicted=own(track.predicted),
                               extra={k: own(v) for k, v in track.extra.items()}, covariance=own(track.covariance),
                               nis=own(track.nis), nis_dof=own(track.nis_dof))


class RTSMixin(GatedFilter):
    """Makes a Kalman-family estimator a smoother: every finished track (from :meth:`finish` or a
    compiled ``run``) gets :func:`rts_smooth` (the streaming ``step`` output stays the filter's);
    ``run_batch`` loops over :meth:`run` so that every track is smoothed. Under
    :func:`filter_passes_shared` a track its filter has just made of the same observations is
    smoothed instead of filtered again."""

    @classmethod
    def smooths(cls) -> str:
        """The name of the filter whose track this smoother's backward pass takes."""
        return next(c.name for c in cls.__mro__[1:] if issubclass(c, Estimator) and not issubclass(c, RTSMixin)
                    and "name" in vars(c))

    def run(self, Y: np.ndarray) -> Track:
        done = None if _PASSES.tracks is None else _PASSES.tracks.get(_pass_key(self, self.smooths(), Y))
        if done is None:
            return super().run(Y)
        return self.complete(_copy_track(done, self.name), self.check(Y))

    def complete(self, track: Track, Y: np.ndarray) -> Track:
        tr = rts_smooth(self, track)
        tr.reprojection_error = reprojection_errors(self.rig, tr.position, Y)
        return tr

    run_batch = Estimator.run_batch
