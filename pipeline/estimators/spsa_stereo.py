"""``spsa_stereo``: an SPSA tracker that tracks — Algorithm 1's ingredients (simultaneous ±1
perturbations, a few cost evaluations per frame, a linear motion prediction, no noise statistics, no
matrix inversion) rearranged so that the update acts on a stereo rig. The perturbations
are a deterministic ±1 sequence, as in Bhatnagar, Fu, Marcus & Wang (2003), *Two-timescale
simultaneous perturbation stochastic approximation using deterministic perturbation sequences*,
ACM TOMACS 13(2): a full cycle of them estimates the gradient without the random cross terms.

Why Algorithm 1 stalls. Its cost pairs two *different* frames and is minimised in metres; the
cost's curvature along depth falls like b²/z² against sideways (on `receding`'s 0.3 m rig it is
120× weaker at 1.5 m and 2,600× at 7.5 m: docs/thesis.md), so a gain small enough to be stable
sideways leaves depth (and velocity) practically unchanged.

What this method does instead, every frame k with observation ``y_k``:

1. **Predict** (linear extremum prediction, as Algorithm 1): ``p⁻ = p + v·dt``, ``v⁻ = v``.
2. **Re-parametrise** the position in the left camera's image coordinates, where the reprojection
   cost is well conditioned at any depth::

       q = g(p) = (x_c/z_c,  y_c/z_c,  x_c/z_c − b/z_c),   (x_c, y_c, z_c) = R_l p + t_l

   (b the baseline): the left image point and, for a rectified rig, the right camera's x, so the
   cost's Hessian is ≈ 2·diag(1, 2, 1). The disparity is ``q₀ − q₂ = b/z_c``. In these coordinates
   each camera's normalized projection is a projective map of ``(q₀, q₁, 1, q₀ − q₂)`` —
   ``M_c (q₀, q₁, 1) + (m_c / b)(q₀ − q₂)`` dehomogenised, ``M_c = R_c R_lᵀ``,
   ``m_c = t_c − M_c t_l`` — the rig's model composed with ``g⁻¹`` (tested equal to it).
3. **Minimise that frame's cost** ``J(q) = ‖h(g⁻¹(q)) − y_k‖²`` (normalized image coordinates)
   from ``q⁻ = g(p⁻)`` by simultaneous-perturbation Newton steps. The perturbations are the four
   cube diagonals ``Δᵢ`` (any three independent, ``Σ ΔᵢΔᵢᵀ = 4I``: a tight frame) in coordinates
   ``q' = (q₀, √2·q₁, q₂)`` where both cameras see ``q₁``, so the Hessian is ≈ 2I (the coordinate
   only a missing camera sees is held)::

       dᵢ = (J(q + cΔᵢ) − J(q − cΔᵢ)) / 2c         (directional derivative, exact for a quadratic)
       hᵢ = (J(q + cΔᵢ) + J(q − cΔᵢ) − 2 J(q)) / c²  (directional curvature, a scalar)
       ∇ = ¼ Σ Δᵢ dᵢ   (exact for a quadratic: the frame is tight)
       h = Σ hᵢ / (4·dim)   (the mean curvature: a scalar, never a matrix)
       q ← q − ∇ / h

   Nine cost evaluations and one division by a scalar; one more evaluates the new point. For a
   rectified rig the cost is exactly quadratic in q with Hessian 2·diag(1, 2, 1), so one step lands
   on the minimum; a toed-in rig or a distant depth makes it a few per cent anisotropic, and the
   step repeats (at most ``max_sweeps`` times) while it moved any coordinate by more than 5c —
   the residual then is a few per cent of the step, well below the pixel noise. A step that
   does not lower the cost is not taken. Result: ``q̂``.
4. **Correct** each of the image coordinates x/z, y/z and the disparity b/z with its own
   growing-memory line-fit gains (Brookner, *Tracking and Kalman Filtering Made Easy*, §1.2.6)::

       α_n = 2(2n − 1) / (n(n + 1)),   β_n / α_n = 3 / (2n − 1)
       s⁺ = s⁻ + α_n (ŝ − s⁻),   p⁺ = g⁻¹(s⁺),   v⁺ = v⁻ + (g⁻¹(s⁻ + β_n (ŝ − s⁻)) − p⁻) / dt

   The memory n of each coordinate grows by one per correction up to where α_n reaches its floor.
   The image coordinates' floor is ``alpha_min``. The disparity's floor is proportional to the
   predicted disparity itself, ``alpha_depth_per_disparity · b/z`` (at least ``alpha_min_depth``):
   a given acceleration moves the disparity by ``b·a/z²`` while its noise stays the same, so the
   tracking index falls like 1/z² and the steady-state gain of a line fit with it like 1/z (Kalata,
   *The tracking index*, IEEE TAES 20(2), 1984: α ≈ √(2λ) for small λ). Near, depth is allowed to
   follow; far, where a disparity error is a large depth error, it is smoothed harder. It starts
   at ``init.frames`` after a fitted start (a line through n frames carries n frames' evidence) and
   at 0 after a given one: the first correction (n = 1) then takes the measured position and keeps
   the given velocity. The velocity is learned from the position steps alone.
5. **Kesten's rule** (Kesten 1958, the classic step-size adaptation of stochastic approximation),
   per coordinate: the memory halves after ``run`` innovations ``ŝ − s⁻`` in a row with the same
   sign (the estimate lags a manoeuvre); white noise alternates in sign.

What the constants encode. There are no noise statistics, but the floors are not free of them: a
floor α fixes the memory n at which α_n reaches it (``alpha_min`` 0.5 → n = 2 frames), and a memory
counted in frames is an assumption about motion against noise *per frame*: the same floor is a
memory of n/30 s at 30 fps and n/120 s at 120 fps, so a faster camera smooths over a shorter time
and a slower one lags more. The disparity's floor ``alpha_depth_per_disparity · b/z`` encodes how
fast depth may change against the disparity noise; ``run`` (Kesten) how many same-signed
innovations in a row count as a manoeuvre. Change the frame rate and these are what to revisit.

Outliers: each camera's squared reprojection residual at the prediction, over σ² and the robust scale of
:class:`~pipeline.estimators.gating.RobustNISScale` (a floor-gain tracker lags manoeuvres, and the median of its
recent residuals widens the gate with the lag), is gated at the χ²₂ quantile ``gate``; ``restart_after`` frames in a
row with a camera gated restart the track from its recent detections. A prediction behind the left camera restarts the
track from the frame's own minimum. A frame whose minimised cost stays above ``cost_gate`` (normalized units² per
camera) is treated as a gap: that catches a detection off the epipolar line (a wrong blob at another height), not one
shifted along it, which the frame's own cost reads as a change of depth. The floors are the tuning knobs, as α is
Algorithm 1's: small for smooth motion, larger to follow manoeuvres.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
from pydantic import Field

from pipeline.core.camera import StereoRig
from pipeline.core.rectify import disparity_maps, rectifying_frame
from pipeline.estimators.base import Estimator, EstimatorConfig, InitConfig, Step, Track, not_started, use_compiled
from pipeline.estimators.gating import RobustNISScale, camera_gate, stereo_consistent
from pipeline.estimators.registration import register
from pipeline.estimators.spsa import normalized_rows

SQRT_HALF = math.sqrt(0.5)
BIG_COST = 1.0e6  # cost of a trial point behind a camera or beyond infinity
#: the four cube diagonals: any three are independent, and Σ DDᵀ = 4I (a tight frame)
DIAGONALS = ((1.0, 1.0, 1.0), (1.0, 1.0, -1.0), (1.0, -1.0, 1.0), (-1.0, 1.0, 1.0))


class SPSAStereoConfig(EstimatorConfig):
    """Gain floors, Newton steps per frame, perturbation size and outlier gates of ``spsa_stereo``."""

    gate: float = Field(0.9995, ge=0.0, lt=1.0)
    """the per-camera χ² gate on the prediction's reprojection (see :meth:`SPSAStereoEstimator._gate_cameras`; 0 turns it
    off); a track gated ``restart_after`` frames in a row restarts from the detections"""

    init: InitConfig = Field(default_factory=lambda: InitConfig(frames=2))
    """starts from a line through the first two triangulations"""
    alpha_min: float = Field(0.5, gt=0, le=1)
    """the floor of the gain α_n of the image coordinates x/z, y/z (the memory stops growing there)"""
    alpha_depth_per_disparity: float = Field(1.5, gt=0)
    """the floor of the disparity's gain is this times the predicted normalized disparity b/z (0.1 at 4.5 m on a 0.3 m
    rig): the disparity's tracking index falls like 1/z²"""
    alpha_min_depth: float = Field(0.02, gt=0, le=1)
    """the disparity's floor never falls below this (very far points)"""
    max_sweeps: int = Field(4, ge=1, le=20)
    """Newton steps at most per frame: another runs only while the last one moved q by more than 5 perturbations (far from
    the minimum: at a start, after a manoeuvre); near it, one"""
    run: int = Field(4, ge=2)
    """corrections in a row with the same innovation sign that halve the memory (Kesten's rule)"""
    perturbation: float = Field(1e-3, gt=0)
    """perturbation size c in normalized image coordinates (1e-3 ≈ 0.6 px at f = 600 px)"""
    cost_gate: float = Field(math.inf, gt=0)
    """a frame whose minimised cost (normalized units², per camera) exceeds this is skipped as an outlier (it catches
    detections off the epipolar line); inf disables this cost gate"""


def max_memory(alpha: float) -> float:
    """The memory n at which the growing-memory gain ``2(2n − 1)/(n(n + 1))`` falls to α."""
    return ((4 - alpha) + math.sqrt((4 - alpha) ** 2 - 8 * alpha)) / (2 * alpha)


@register
class SPSAStereoEstimator(Estimator):
    """SPSA on each frame's cost in image/disparity coordinates, decreasing gains (tracks)."""

    rig: StereoRig  # a stereo pair only (any_cameras is False: the base refuses a Rig)
    name = "spsa_stereo"
    min_frames = 2
    Config = SPSAStereoConfig
    config: SPSAStereoConfig  # the validated settings, of this method's own type

    def reset(self) -> None:
        super().reset()
        if not hasattr(self, "_Rl"):
            self._constants()
        self._scale = RobustNISScale(self.config.pixel_sigma)
        self._gated_run = 0  # frames in a row with a camera gated (restart after cfg.restart_after)
        self._gated: int = 0  # this frame's cameras gated
        self.p = [0.0, 0.0, 0.0]
        self.v = [0.0, 0.0, 0.0]

    def _constants(self) -> None:
        """What the rig and the settings fix, computed at the first reset (neither changes after)."""
        cfg = self.config
        self._unit_rig = self.rig.normalized()  # triangulates normalized observations (restarts)
        R0, t0 = rectifying_frame(self.rig)  # q lives in this frame: any layout is a "right" one
        self._Rl = R0.ravel().tolist()
        self._tl = t0.tolist()
        self._b = self.rig.baseline
        self._Al, self._Ar = disparity_maps(self.rig)
        self._nmax_image = max_memory(cfg.alpha_min)
        self._kd, self._amin_d = cfg.alpha_depth_per_disparity, cfg.alpha_min_depth
        self._runlen = cfg.run
        self._c = cfg.perturbation
        self._far = 5.0 * cfg.perturbation
        self._sweeps = cfg.max_sweeps
        self._gate = cfg.cost_gate
        self._nis_gate = camera_gate(cfg.gate)
        self._f2 = [float(c.K[0, 0] * c.K[1, 1]) for c in self.rig.cameras]  # px² per normalized unit²
        self._poses = [(c.R.ravel().tolist(), c.t.ravel().tolist()) for c in self.rig.cameras]  # for the gate
        self._prm: Any = None  # the compiled core's parameters (:meth:`_parameters`)

    @property
    def x(self) -> np.ndarray:
        """State ``[p; v]`` (m, m/s)."""
        return np.array(self.p + self.v)

    def g(self, p) -> list[float] | None:
        """``q = (x_c/z_c, y_c/z_c, x_c/z_c − b/z_c)`` of a world point in the rectifying frame (the
        left camera's image coordinates there, and the second camera's x); None behind it."""
        R, t = self._Rl, self._tl
        x = R[0] * p[0] + R[1] * p[1] + R[2] * p[2] + t[0]
        y = R[3] * p[0] + R[4] * p[1] + R[5] * p[2] + t[1]
        z = R[6] * p[0] + R[7] * p[1] + R[8] * p[2] + t[2]
        if z <= 1e-9:
            return None
        return [x / z, y / z, (x - self._b) / z]

    def g_inv(self, q0: float, q1: float, q2: float) -> tuple[float, float, float]:
        """``g⁻¹(q)``: back to world coordinates (``Rᵀ (p_c − t)``, ``z_c = b / (q₀ − q₂)``)."""
        R, t = self._Rl, self._tl
        z = self._b / (q0 - q2)
        a, b, c = q0 * z - t[0], q1 * z - t[1], z - t[2]
        return (R[0] * a + R[3] * b + R[6] * c, R[1] * a + R[4] * b + R[7] * c, R[2] * a + R[5] * b + R[8] * c)

    def cost(self, q0: float, q1: float, q2: float, yn: tuple, use_l: bool, use_r: bool) -> float:
        """``J(q) = ‖h(g⁻¹(q)) − y‖²`` in normalized image coordinates over the cameras in use,
        through :func:`~pipeline.core.rectify.disparity_maps`; ``BIG_COST`` beyond infinity or behind a camera."""
        s0, s1, s2 = q0, q1, q0 - q2
        if s2 <= 1e-12:
            return BIG_COST
        c = 0.0
        for use, A, i in ((use_l, self._Al, 0), (use_r, self._Ar, 2)):
            if use:
                w = A[8] * s0 + A[9] * s1 + A[10] + A[11] * s2
                if w <= 1e-12:
                    return BIG_COST
                du = (A[0] * s0 + A[1] * s1 + A[2] + A[3] * s2) / w - yn[i]
                dv = (A[4] * s0 + A[5] * s1 + A[6] + A[7] * s2) / w - yn[i + 1]
                c += du * du + dv * dv
        return c

    def _start_memory(self) -> float:
        """Evidence a start carries: the fitted frames, or none for a given state."""
        init = self.config.init
        return float(init.frames) if init.mode == "triangulation" else 0.0

    def _begin(self, state, memory: float) -> None:
        """Start from ``state = [p; v]`` with ``memory`` frames' worth of evidence per coordinate."""
        self.p, self.v = list(state[:3]), list(state[3:])
        self._mem = [float(memory)] * 3
        self._run = [0, 0, 0]
        self._sgn = [0.0, 0.0, 0.0]
        self.initialized = True

    def _minimise(self, q: list[float], yn: tuple, use_l: bool, use_r: bool) -> tuple[float, float, float, float]:
        """Simultaneous-perturbation Newton steps on this frame's cost from ``q`` (module docstring,
        step 3); (q̂₀, q̂₁, q̂₂, J(q̂))."""
        c, J = self._c, self.cost
        q0, q1, q2 = q
        J0 = J(q0, q1, q2, yn, use_l, use_r)
        # with one camera its x moves q₀ and q₂ together: the disparity (depth) is what it cannot see
        one = use_l != use_r
        s1 = SQRT_HALF if (use_l and use_r) else 1.0  # both cameras see q₁: twice the curvature
        dim = 2.0 if one else 3.0
        for _ in range(self._sweeps):
            g0 = g1 = g2 = hsum = 0.0
            for D in DIAGONALS:
                d0, d1 = D[0], D[1] * s1
                d2 = D[0] if one else D[2]
                Jp = J(q0 + c * d0, q1 + c * d1, q2 + c * d2, yn, use_l, use_r)
                Jm = J(q0 - c * d0, q1 - c * d1, q2 - c * d2, yn, use_l, use_r)
                d = Jp - Jm
                g0 += D[0] * d
                g1 += D[1] * d
                g2 += (D[0] if one else D[2]) * d
                hsum += Jp + Jm - 2.0 * J0
            if not hsum > 0.0:
                break
            # ∇' = Σ Dᵢ dᵢ / 4 with dᵢ = (J₊ − J₋)/2c; h = Σ hᵢ / (4·dim) with hᵢ = (J₊ + J₋ − 2J)/c²
            k = dim * c / (2.0 * hsum)  # Newton step −∇'/h = −k·(g0, g1, g2), back to q through s₁
            t0, t1, t2 = k * g0, k * g1 * s1, k * g2
            while (q0 - t0) - (q2 - t2) <= 1e-12:  # would cross infinity: shorten
                t0, t1, t2 = 0.5 * t0, 0.5 * t1, 0.5 * t2
            J1 = J(q0 - t0, q1 - t1, q2 - t2, yn, use_l, use_r)
            if not J1 < J0:  # no decrease: the model is poor this far out; keep q
                break
            q0, q1, q2, J0 = q0 - t0, q1 - t1, q2 - t2, J1
            if max(abs(t0), abs(t1), abs(t2)) < self._far:  # near: the remaining error is a few % of this step
                break
        return q0, q1, q2, J0

    def disparity_memory_cap(self, disparity: float) -> float:
        """The disparity's memory cap at a predicted normalized disparity b/z: where α reaches
        ``alpha_depth_per_disparity · b/z`` (at least ``alpha_min_depth``, at most 1)."""
        return max_memory(min(1.0, max(self._amin_d, self._kd * disparity)))

    def _gains(self, n: float) -> tuple[float, float]:
        """(α, β/α) of the growing-memory line fit after n corrections (Brookner §1.2.6). The first
        correction after a given start (n = 1) takes the measured position and keeps the velocity:
        a prior of unknown quality is not a measurement to difference against."""
        if n <= 1.0:
            return 1.0, 0.0
        return 2.0 * (2 * n - 1) / (n * (n + 1)), 3.0 / (2 * n - 1)

    def _memory(self, i: int, e: float, cap: float) -> float:
        """Kesten's rule per coordinate: the memory n grows by one while the innovation's sign
        alternates (noise) and halves after ``run`` corrections in a row with the same sign (lag);
        capped at ``cap``, where α reaches its floor."""
        same = (e > 0.0) == (self._sgn[i] > 0.0)
        self._sgn[i] = e
        self._run[i] = self._run[i] + 1 if same else 0
        if self._run[i] >= self._runlen:
            self._mem[i] = max(1.0, 0.5 * self._mem[i])
            self._run[i] = 0
        else:
            self._mem[i] = min(self._mem[i] + 1.0, cap)
        return self._mem[i]

    def _update(self, yn: tuple, use_l: bool, use_r: bool, y: np.ndarray) -> tuple[bool, float, float]:
        """One frame after the start (predict, minimise, correct) on a normalized observation;
        (predicted, minimised cost, image-coordinate gain α_n). The state is left in ``self.p``,
        ``self.v``."""
        dt = self.dt
        p, v = self.p, self.v
        pp = [p[0] + v[0] * dt, p[1] + v[1] * dt, p[2] + v[2] * dt]
        self.p = pp
        if not (use_l or use_r):
            return True, math.nan, math.nan
        if math.isfinite(self._nis_gate):
            use_l, use_r = self._gate_cameras(pp, yn, use_l, use_r, y)
            if not (use_l or use_r):
                return True, math.nan, math.nan
        q = self.g(pp)
        if q is None:  # the prediction left the field of view behind the camera: start again
            q = self.g(self._unit_rig.triangulate(np.array(yn))) if use_l and use_r else None
            if q is None or not all(math.isfinite(c) for c in q) or q[0] - q[2] <= 1e-12:
                return True, math.nan, math.nan
            h0, h1, h2, cost = self._minimise(q, yn, True, True)
            self._begin((*self.g_inv(h0, h1, h2), 0.0, 0.0, 0.0), 1.0)
            return False, cost, 1.0
        h0, h1, h2, cost = self._minimise(q, yn, use_l, use_r)
        if cost > self._gate * (int(use_l) + int(use_r)):
            return True, cost, math.nan
        e0, e1, ed = h0 - q[0], h1 - q[1], (h0 - h2) - (q[0] - q[2])
        dd = q[0] - q[2]  # the predicted disparity b/z sets the disparity's floor
        a0, r0 = self._gains(self._memory(0, e0, self._nmax_image))
        a1, r1 = self._gains(self._memory(1, e1, self._nmax_image))
        ad, rad = self._gains(self._memory(2, ed, self.disparity_memory_cap(dd)))
        # the correction in (x/z, y/z, b/z): image coordinates and disparity have their own gains
        d_new = dd + ad * ed
        if d_new <= 1e-12:  # a correction beyond infinity: keep the predicted disparity
            d_new = dd
        x0, x1 = q[0] + a0 * e0, q[1] + a1 * e1
        pn = self.g_inv(x0, x1, x0 - d_new)
        d_vel = dd + rad * ad * ed
        x0v, x1v = q[0] + r0 * a0 * e0, q[1] + r1 * a1 * e1
        pv = self.g_inv(x0v, x1v, x0v - d_vel) if d_vel > 1e-12 else pn
        self.p = list(pn)
        k = 1.0 / dt
        self.v = [v[0] + k * (pv[0] - pp[0]), v[1] + k * (pv[1] - pp[1]), v[2] + k * (pv[2] - pp[2])]
        return False, cost, a0

    def _gate_cameras(self, pp: list[float], yn: tuple, use_l: bool, use_r: bool,
                      pixels: np.ndarray) -> tuple[bool, bool]:
        """Drop a camera whose observation lies too far from the prediction: its squared
        reprojection residual (px²) over ``σ²`` times the robust scale of
        :class:`~pipeline.estimators.gating.RobustNISScale`, beyond the χ² gate (2 dof). The
        prediction is projected in Python floats (normalized coordinates: ``R p + t``, divided)."""
        if not all(math.isfinite(c) for c in pp):
            return use_l, use_r
        out = [use_l, use_r]
        sigma2 = self.config.pixel_sigma**2
        for c in (0, 1):
            if out[c]:
                R, t = self._poses[c]
                x = R[0] * pp[0] + R[1] * pp[1] + R[2] * pp[2] + t[0]
                y = R[3] * pp[0] + R[4] * pp[1] + R[5] * pp[2] + t[1]
                z = R[6] * pp[0] + R[7] * pp[1] + R[8] * pp[2] + t[2]
                nis = ((x / z - yn[2 * c]) ** 2 + (y / z - yn[2 * c + 1]) ** 2) * self._f2[c] / sigma2
                scale = self._scale.value
                self._scale.add([nis])
                if nis / scale > self._nis_gate:
                    out[c] = False
                    self._gated += 1
        # both far but one point (``pixels``: this frame's observation): lag, not an outlier
        if self._gated == 2 and stereo_consistent(self.model, pixels, self.config.pixel_sigma,
                                                  self.config.gate):
            self._gated = 0
            return use_l, use_r
        return out[0], out[1]

    def _step(self, y: np.ndarray) -> Step:
        if not self.initialized:
            st = self.start(y)
            if st is None:
                return not_started()
            self._begin(st.state.tolist(), self._start_memory())
            return Step(np.array(self.p), np.array(self.v))
        yn = tuple(self.rig.normalize(y).tolist())
        self._gated = 0
        use_l, use_r = math.isfinite(yn[0]) and math.isfinite(yn[1]), math.isfinite(yn[2]) and math.isfinite(yn[3])
        pred, cost, gain = self._update(yn, use_l, use_r, y)
        restarted = self._restart_if_lost(self.frame, self.recent_observations(), use_l or use_r)
        return Step(np.array(self.p), np.array(self.v), predicted=pred and not restarted,
                    extra={"cost": cost, "gain": gain, "gated": float(self._gated), "restart": float(restarted)})

    def _restart_if_lost(self, frame: int, recent: np.ndarray, had: bool) -> bool:
        """After ``restart_after`` frames in a row with a camera gated (a track that has lost its
        marker, not occasional outliers), start again from this frame's detections when they
        triangulate plausibly; frames without observations leave the count as it is."""
        self._gated_run = self._gated_run + 1 if self._gated else (0 if had else self._gated_run)
        if self._gated_run < self.config.restart_after:
            return False
        s = self.initiator.restart(frame, recent)
        if s is None:
            return False
        self._gated_run = 0
        self._begin(s.state.tolist(), self._start_memory())
        return True

    def _fast(self, Y: np.ndarray) -> tuple[list, list, list, list, list, list]:
        """Every frame from a fresh state in one loop without per-frame objects (observations
        normalized at once): the same arithmetic as repeated :meth:`step`."""
        self.reset()
        n = len(Y)
        rows, okl, okr = normalized_rows(self.rig, Y)
        nan6 = [math.nan] * 6
        states, pred, costs, gains = [nan6] * n, [True] * n, [math.nan] * n, [math.nan] * n
        start = self.initiator.first(Y)
        k = n
        if start is not None:
            self._begin(start.state.tolist(), self._start_memory())
            k = start.frame
            states[k], pred[k] = self.p + self.v, False
            k += 1
        update = self._update
        gated = [math.nan] * (k + 1 if start is not None else n) + [0.0] * (n - k - 1 if start is not None else 0)
        restarts = [math.nan] * len(gated)
        for j in range(k, n):
            self._gated = 0
            pred[j], costs[j], gains[j] = update(tuple(rows[j]), okl[j], okr[j], Y[j])
            restarted = self._restart_if_lost(j, Y[max(0, j + 1 - self.config.restart_after) : j + 1], okl[j] or okr[j])
            pred[j] = pred[j] and not restarted
            states[j] = self.p + self.v
            gated[j], restarts[j] = float(self._gated), float(restarted)
        self.frame = n
        return states, pred, costs, gains, gated, restarts

    def _parameters(self) -> Any:
        """Everything :func:`kernels.spsa_stereo_frames` reads besides the frames and the track: a
        ``PARAMS`` record (made once)."""
        import pipeline.estimators.compiled as kernels

        if self._prm is not None and self._prm.dtype == kernels.PARAMS:
            return self._prm
        c = self.config
        self._prm = kernels.new_stereo_params(
            R=self._Rl, t=self._tl, b=self._b, AL=self._Al, AR=self._Ar, poses=[[*R, *t] for R, t in self._poses],
            f2=self._f2, dt=self.dt, c=self._c, far=self._far, sweeps=self._sweeps, cost_gate=self._gate,
            nis_gate=self._nis_gate, sigma2=c.pixel_sigma**2, nmax=self._nmax_image, kd=self._kd, amin_d=self._amin_d,
            runlen=self._runlen, restart=c.restart_after)
        return self._prm

    def _compiled(self, Y: np.ndarray) -> tuple:
        """:meth:`_fast` through :func:`kernels.spsa_stereo_frames`. Where the kernel stops, this
        asks the initiator for a restart, or computes what a frame needs and only Python has (both
        cameras gated: whether the detections are one point; a prediction behind the cameras: the
        frame's triangulation), and lets the kernel run that frame again."""
        import pipeline.estimators.compiled as kernels

        self.reset()
        n = len(Y)
        states, pred = np.full((n, 6), np.nan), np.ones(n, dtype=bool)
        costs, gains, gated, restarts = (np.full(n, np.nan) for _ in range(4))
        start = self.initiator.first(Y)
        if start is not None:
            rows = self.rig.normalize(Y)
            okl, okr = np.isfinite(rows[:, :2]).all(axis=1), np.isfinite(rows[:, 2:]).all(axis=1)
            prm = self._parameters()
            track = kernels.new_stereo_track(self._scale.minimum)
            t = track.t
            kernels.st_begin(t, *start.state, self._start_memory())
            states[start.frame], pred[start.frame] = kernels.state_of(t), False
            frames = kernels.StereoFrames(rows, okl, okr, np.full(n, np.nan), np.full((n, 4), np.nan))
            consistent, tri = frames.consistent, frames.tri
            out = kernels.StereoOutput(states, pred, costs, gains, gated, restarts)
            j, ra = start.frame + 1, self.config.restart_after
            while j < n:
                j, why = kernels.spsa_stereo_frames(frames, j, prm, track, out)
                if why == kernels.ST_CONSISTENT:
                    consistent[j] = stereo_consistent(self.model, Y[j], self.config.pixel_sigma, self.config.gate)
                elif why == kernels.ST_TRI:
                    tri[j] = (*self._unit_rig.triangulate(rows[j]), 1.0)
                elif why == kernels.ST_RESTART:
                    s = self.initiator.restart(j, Y[max(0, j + 1 - ra) : j + 1])
                    if s is not None:
                        kernels.st_begin(t, *s.state, self._start_memory())
                        t.grun = 0.0
                        states[j], pred[j], restarts[j] = kernels.state_of(t), False, 1.0
                    j += 1
        self.frame = n
        return states, pred, costs, gains, gated, restarts

    def run(self, Y: np.ndarray) -> Track:
        """The clip through the compiled core (:meth:`_compiled`, the kernels compiled or loaded
        before the timing starts), or through :meth:`_fast` where compiling would not pay
        (:func:`~pipeline.estimators.base.use_compiled`); a warm-up on the first frames outside the timing."""
        Y = self.check(Y)
        if use_compiled(len(Y)):
            import pipeline.estimators.compiled as kernels

            kernels.warm_up("spsa_stereo_frames")
            frames = self._compiled
        else:
            frames = self._fast
            frames(Y[: self.warmup_frames])
        t0 = time.perf_counter()
        states, pred, costs, gains, gated, restarts = frames(Y)
        elapsed = time.perf_counter() - t0
        n = len(Y)
        S = np.array(states, dtype=float).reshape(n, 6)
        extra = {"cost": np.array(costs, dtype=float), "gain": np.array(gains, dtype=float),
                 "gated": np.array(gated, dtype=float), "restart": np.array(restarts, dtype=float)}
        return self.make_track(S[:, :3], S[:, 3:], np.array(pred, dtype=bool), elapsed / max(n, 1), Y, extra)
