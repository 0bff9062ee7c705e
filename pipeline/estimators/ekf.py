"""Extended Kalman filter on the stereo reprojection (Krivokon 2011, App. I).

Model of :mod:`pipeline.estimators.base`; with ``H_k = ∂h/∂x`` at the prediction (the measurement
model's analytic ``jacobian``, zeros for the velocity)::

    x⁻ = A x,            P⁻ = A P Aᵀ + Q
    S = H P⁻ Hᵀ + R,      K = P⁻ Hᵀ S⁻¹
    x = x⁻ + K (y − h(x⁻)),  P = (I − K H) P⁻ (I − K H)ᵀ + K R Kᵀ   (Joseph form, as filterpy)

``step`` runs filterpy's ``ExtendedKalmanFilter`` equations written out in numpy (a test holds
them equal to filterpy itself, driven directly, to 1e-9; the per-call checks filterpy makes cost
about as much as the arithmetic). ``run`` on a long clip and ``run_batch`` run the same arithmetic
compiled (:func:`pipeline.estimators.compiled.ekf_frames`, tested equal to ``step``). A camera
without a detection drops its two rows. ``ekf_rts`` adds the Rauch–Tung–Striebel backward pass
(the transition is linear, so filterpy's smoother applies as it is; long clips use its compiled
twin).
"""

from __future__ import annotations

import time
from types import ModuleType
from typing import Any

import numpy as np

from pipeline.core.chi2 import chi2_upper
from pipeline.estimators.base import (
    Estimator,
    Start,
    Step,
    Track,
    not_started,
    transition,
    use_compiled,
    white_noise_acceleration,
)
from pipeline.estimators.gating import JOINT_GATE
from pipeline.estimators.kalman_common import (
    GatedFilter,
    KalmanConfig,
    RTSMixin,
    available_rows,
    drifted,
    filtered_step,
    gated_step,
)
from pipeline.estimators.registration import register


@register
class EKFEstimator(GatedFilter, Estimator):
    """Extended Kalman filter on the stereo (or N-camera) reprojection (white-noise acceleration)."""

    name = "ekf"
    any_cameras = True
    joint_check = True
    Config = KalmanConfig
    config: KalmanConfig  # the validated settings, of this method's own type
    models_time_offset = True

    def reset(self) -> None:
        super().reset()
        cfg = self.config
        self.A = transition(self.dt)
        self.Q = white_noise_acceleration(self.dt, cfg.process_noise * cfg.q_scale)
        self.R = self.model.covar() * cfg.r_scale
        self._x = np.zeros(6)
        self._P = np.eye(6)
        self._I = np.eye(6)
        self._R_rows: dict[tuple[int, ...], np.ndarray] = {}  # the noise of each set of available rows
        self.y: np.ndarray | None = None  # the last update's innovation and its covariance (filterpy's names)
        self.S: np.ndarray | None = None

    @property
    def x(self) -> np.ndarray:
        return self._x

    @property
    def P(self) -> np.ndarray:
        return self._P

    def _step(self, y: np.ndarray) -> Step:
        """filterpy's ``ExtendedKalmanFilter`` predict/update written out in numpy (the same
        arithmetic, tested equal to it; faster without its per-call checks and reshapes)."""
        if not self.initialized:
            s = self.start(y)
            if s is None:
                return not_started()
            self._x, self._P = s.state.copy(), s.covariance.copy()
            self.initialized = True
            return filtered_step(self._x, self._P, False)
        A = self.A
        x = A @ self._x
        P = A @ self._P @ A.T + self.Q
        h_all, H_all = self.model.linearize(x)
        PHt = P @ H_all.T  # both cameras' S, shared by the gate and a full update
        S_all = H_all @ PHt + self.R
        n_gated = 0
        if self.config.gate > 0:
            y, n_gated, restart = self.gate(y, x, P, h_all, H_all, S_all)
            if restart is not None:
                self._x, self._P = restart.state.copy(), restart.covariance.copy()
                return gated_step(filtered_step(self._x, self._P, False), n_gated, True)
        rows = available_rows(y)
        if not len(rows):
            self._x, self._P = x, P
            return gated_step(Step(x[:3].copy(), x[3:].copy(), True, P), n_gated)
        x, P, r, S, nis = self._update(x, P, y, rows, h_all, H_all, PHt, S_all)
        self._x, self._P, self.y, self.S = x, P, r, S
        return gated_step(Step(x[:3].copy(), x[3:].copy(), False, P, r, S, known_nis=nis), n_gated)

    def _update(self, x, P, y, rows, h_all, H_all, PHt_all, S_all):
        """The Joseph-form update on the rows present: (x, P, innovation, S, NIS)."""
        if len(rows) == len(h_all):
            H, r, R, PHt, S = H_all, y - h_all, self.R, PHt_all, S_all
        else:
            H, r = H_all[rows], y[rows] - h_all[rows]
            key = rows.tobytes()
            if key not in self._R_rows:
                self._R_rows[key] = self.R[np.ix_(rows, rows)]
            R = self._R_rows[key]
            PHt = P @ H.T
            S = H @ PHt + R
        Si = np.linalg.inv(S)
        K = PHt @ Si
        IKH = self._I - K @ H
        return x + K @ r, IKH @ P @ IKH.T + K @ R @ K.T, r, S, float(r @ Si @ r)

    def run(self, Y: np.ndarray) -> Track:
        """The clip through the compiled core (:func:`kernels.ekf_frames`, the arithmetic of
        repeated :meth:`step`; the kernels compiled or loaded before the timing starts), or step by
        step where compiling would not pay (:func:`~pipeline.estimators.base.use_compiled`)."""
        Y = self.check(Y)
        if not use_compiled(len(Y)) or self.rig.n != 2:  # the compiled core is written for two cameras
            return Estimator.run(self, Y)
        import pipeline.estimators.compiled as kernels

        kernels.warm_up("ekf_frames")
        t0 = time.perf_counter()
        a = self._compiled(Y)
        elapsed = (time.perf_counter() - t0) / max(len(Y), 1)
        if not np.isfinite(a["pos"]).any():  # never started: as finish makes it from the steps
            return self.make_track(a["pos"], a["vel"], a["pred"], elapsed, Y)
        extra = {"gated": a["gated"], "restart": a["restart"]} if np.isfinite(a["gated"]).any() else {}
        updated = a["dof"].any()
        return self.make_track(a["pos"], a["vel"], a["pred"], elapsed, Y, extra, a["cov"], a["nis"] if updated else None,
                               a["dof"] if updated else None)

    def _compiled(self, Y: np.ndarray, start: Start | bool | None = False) -> dict[str, np.ndarray]:
        """Per-frame arrays of the filter over one clip from a fresh state (``start``: the
        initiator's start when the caller has it)."""
        import pipeline.estimators.compiled as kernels

        self.reset()
        n = len(Y)
        a = {k: np.full(shape, np.nan) for k, shape in
             (("pos", (n, 3)), ("vel", (n, 3)), ("cov", (n, 6, 6)), ("nis", n), ("gated", n), ("restart", n))}
        a["pred"], a["dof"] = np.ones(n, dtype=bool), np.zeros(n, dtype=np.int64)
        s = self.initiator.first(Y) if isinstance(start, bool) else start
        if s is None:
            return a
        x, P = s.state.copy(), s.covariance.copy()
        a["pos"][s.frame], a["vel"][s.frame], a["cov"][s.frame], a["pred"][s.frame] = x[:3], x[3:], P, False
        cfg, model = self.config, self._kernel_model(kernels)
        track = kernels.new_track(x, P)
        out = kernels.EKFOutput(a["pos"], a["vel"], a["cov"], a["pred"], a["nis"], a["dof"], a["gated"], a["restart"])
        k, resume = s.frame + 1, 0
        while k < n:
            k = kernels.ekf_frames(Y, k, resume, model, track, out)
            if k < n:  # gated too long (or back from a one-camera stretch): a restart, if they triangulate
                asked = bool(track.gate.camera.any()) or drifted(self.model, track.scratch_x, Y[k], cfg.gate)
                r = self.initiator.restart(k, Y[max(0, k + 1 - cfg.restart_after) : k + 1]) if asked else None
                resume = 2 if r is None else 1
                if r is not None:
                    x[:], P[:] = r.state, r.covariance
        self.frame = n
        return a

    def _kernel_model(self, kernels: ModuleType) -> Any:
        """What the compiled core takes of the filter (an ``EKFModel`` of ``kernels``): both cameras'
        3 × 4 matrices, the time offset, the noises and the gate's threshold (inf: no gate)."""
        threshold = self.gate_threshold() if self.config.gate > 0 else np.inf
        joint = chi2_upper(4, JOINT_GATE) if self.joint_check and np.isfinite(threshold) else np.inf
        return kernels.EKFModel(np.stack([c.P for c in self.rig.cameras]), self.model.time_offset, self.dt, self.Q,
                                self.R, threshold, self.config.restart_after, joint)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """The filter over M tracks (M × frames × 4 → M × frames × 3): the starts found for all
        tracks at once, then every track through the compiled batch core; a track that asks for a
        restart (the initiator is Python) runs again on its own through :meth:`_compiled`."""
        import pipeline.estimators.compiled as kernels

        if self.rig.n != 2:
            return Estimator.run_batch(self, Y)
        Y = np.asarray(Y, dtype=float)
        self.reset()
        M, n = Y.shape[:2]
        out = np.full((M, n, 3), np.nan)
        starts = self.initiator.first_batch(Y) if M else []
        begin = np.array([s.frame if s is not None else n for s in starts], dtype=np.int64)
        x0 = np.array([s.state if s is not None else np.zeros(6) for s in starts]).reshape(M, 6)
        P0 = np.array([s.covariance if s is not None else np.eye(6) for s in starts]).reshape(M, 6, 6)
        scratch = kernels.new_track(np.zeros(6), np.eye(6))
        stopped = kernels.ekf_batch(Y, begin, x0, P0, self._kernel_model(kernels), scratch, out)
        for m in np.flatnonzero(stopped < n):
            out[m] = self._compiled(Y[m], starts[m])["pos"]
        return out


@register
class EKFRTSEstimator(RTSMixin, EKFEstimator):
    """ekf followed by a Rauch–Tung–Striebel backward pass (offline smoothing)."""

    name = "ekf_rts"
