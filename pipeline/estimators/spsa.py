"""Algorithm 1 of Krivokon (2011): nonstationary SPSA with linear extremum prediction.

State ``θ ∈ R⁶`` (position, velocity); random perturbation ``Δ_k`` with components ±1/√6. For
iteration k, consuming frames 2k−1 and 2k::

    x_{2k−1} = A (θ_{2k−2} − βΔ_k),        x_{2k} = A² (θ_{2k−2} + βΔ_k)
    z_j = ‖h(x_j) − y_j‖²                   (normalized image coordinates)
    d = (z_{2k} − z_{2k−1}) / (2β),          d ← sign(d)·th if |d| > th   (projection rule)
    θ_{2k−1} = A θ_{2k−2},                  θ_{2k} = A² θ_{2k−2} − α Δ_k d

α, β, th are the only parameters; no noise statistics, two measurements per iteration, no matrix
inversion. ``th: null`` switches the projection rule off (the thesis's Fig. 6 runaway).

The iteration runs in frame units, as the thesis does (``A`` with unit steps): the state's second
half is the displacement per frame ``v·dt``, so one β perturbs position and velocity comparably;
velocities are reported in m/s. The cost is computed in normalized image coordinates
(``(u − cx)/fx``, ``(v − cy)/fy``) so α, β, th do not depend on resolution. A camera missing in
either frame of a pair is left out of both costs; with no camera in common the iteration only
predicts. The single-track step is written in plain Python scalars (a 6-vector is too small for
numpy to pay off); ``run`` on a long clip and ``run_batch`` run the same iteration compiled
(:func:`pipeline.estimators.compiled.spsa_frames`, tested equal to ``step``).
"""

from __future__ import annotations

import math
import time

import numpy as np
from pydantic import Field

from pipeline.core.camera import StereoRig
from pipeline.estimators.base import Estimator, EstimatorConfig, InitConfig, Start, Step, Track, not_started, use_compiled
from pipeline.estimators.registration import register

BIG_COST = 1.0e6  # cost of a trial point behind a camera (keeps the iteration finite)


class SPSAConfig(EstimatorConfig):
    """Algorithm 1's step size α, perturbation size β and projection threshold th.

    SPSA learns velocity slowly, so by default it starts from a line fitted to the first five
    triangulations (``init.frames = 5``) instead of a zero velocity. The thesis gives no values for
    our units; α = 0.1, th = 0.03 are the largest in a grid (α 0.01–10, th 0.003–∞) that stayed
    bounded on the ``receding`` and ``maneuvering`` scenarios at 1.5 px. The earlier α = 0.03,
    th = 0.003 capped a step at 3.7e-5 m per iteration: the update was inert.
    """

    init: InitConfig = Field(default_factory=lambda: InitConfig(frames=5))
    """starts from a line fitted through the first five triangulations (SPSA learns velocity slowly)"""
    alpha: float = Field(0.1, gt=0)
    """step size α of the update θ ← θ − α d Δ"""
    beta: float = Field(0.01, gt=0)
    """perturbation size β of the trial points θ ± β Δ"""
    th: float | None = Field(0.03, gt=0)
    """projection threshold on |d|; None switches the rule off"""


def _cost(p0: float, p1: float, p2: float, yn: tuple, use_l: bool, use_r: bool, cams: tuple) -> float:
    """``‖h(p) − y‖²`` in normalized coordinates over the cameras in use: the measurement model of
    :meth:`StereoRig.normalized` written out in plain floats for speed (tested equal to it to
    1e-12); a trial point behind a camera costs ``BIG_COST``. ``cams``: :func:`camera_tuples`."""
    c = 0.0
    if use_l:
        r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2 = cams[0]
        z = r20 * p0 + r21 * p1 + r22 * p2 + t2
        if z <= 1e-9:
            return BIG_COST
        du = (r00 * p0 + r01 * p1 + r02 * p2 + t0) / z - yn[0]
        dv = (r10 * p0 + r11 * p1 + r12 * p2 + t1) / z - yn[1]
        c += du * du + dv * dv
    if use_r:
        r00, r01, r02, r10, r11, r12, r20, r21, r22, t0, t1, t2 = cams[1]
        z = r20 * p0 + r21 * p1 + r22 * p2 + t2
        if z <= 1e-9:
            return BIG_COST
        du = (r00 * p0 + r01 * p1 + r02 * p2 + t0) / z - yn[2]
        dv = (r10 * p0 + r11 * p1 + r12 * p2 + t1) / z - yn[3]
        c += du * du + dv * dv
    return c


def camera_tuples(rig) -> tuple[tuple, tuple]:
    """Both cameras' ``(R, t)`` as plain-float tuples for :func:`_cost`."""
    left, right = (tuple([*c.R.ravel().tolist(), *np.ravel(c.t).tolist()]) for c in rig.cameras)
    return left, right


def normalized_rows(rig, Y: np.ndarray) -> tuple[list, list, list]:
    """A clip's observations through the camera model at once, as plain-float rows, with which
    cameras are present per frame: ``(rows, left_ok, right_ok)`` for the single-track fast loops."""
    Yn = rig.normalize(Y)
    ok = np.isfinite(Yn)
    return Yn.tolist(), (ok[:, 0] & ok[:, 1]).tolist(), (ok[:, 2] & ok[:, 3]).tolist()


def delta_sequence(seed: int, count: int, dim: int) -> np.ndarray:
    """The first ``count`` perturbations Δ (components ±1/√dim) a track with this seed draws: the
    same blocks of 256 from the same generator as :meth:`SPSAEstimator._draw_delta`."""
    rng, a = np.random.default_rng(seed), 1.0 / math.sqrt(dim)
    blocks = [np.where(rng.integers(0, 2, size=(256, dim)) == 1, a, -a) for _ in range(max(1, -(-count // 256)))]
    return np.vstack(blocks)[:count]


@register
class SPSAEstimator(Estimator):
    """Algorithm 1 (SPSA with linear prediction and the projection rule)."""

    rig: StereoRig  # a stereo pair only (any_cameras is False: the base refuses a Rig)
    name = "spsa"
    min_frames = 2
    Config = SPSAConfig
    config: SPSAConfig  # the validated settings, of this method's own type
    state_dim = 6

    def reset(self) -> None:
        super().reset()
        self._cams = camera_tuples(self.rig)
        cfg = self.config
        self._alpha, self._beta = cfg.alpha, cfg.beta
        self._th = math.inf if cfg.th is None else cfg.th
        self.theta = [0.0] * 6  # frame units: [p, v·dt]
        self._phase = 0  # 0: next frame is x_{2k−1}; 1: next frame is x_{2k}
        self._delta: list[float] = []
        self._z_odd: tuple[float, ...] | None = None
        self._y_odd: tuple = ()
        self._deltas: list[list[float]] = []
        self._sign_i = 0

    @property
    def x(self) -> np.ndarray:
        """State in SI units ``[p, v]``."""
        t = self.theta
        return np.array([t[0], t[1], t[2], t[3] / self.dt, t[4] / self.dt, t[5] / self.dt])

    def _normalize(self, y: np.ndarray) -> tuple[tuple, bool, bool]:
        """Normalized observation (through the camera model) and which cameras are present."""
        out = tuple(self.rig.normalize(y).tolist())
        return out, math.isfinite(out[0]) and math.isfinite(out[1]), math.isfinite(out[2]) and math.isfinite(out[3])

    def _draw_delta(self) -> list[float]:
        """Next perturbation Δ (components ±1/√d), drawn from the seeded generator in blocks."""
        if self._sign_i >= len(self._deltas):
            a = 1.0 / math.sqrt(self.state_dim)
            self._deltas = np.where(self.rng.integers(0, 2, size=(256, self.state_dim)) == 1, a, -a).tolist()
            self._sign_i = 0
        self._sign_i += 1
        return self._deltas[self._sign_i - 1]

    def _out(self, th: list[float], predicted: bool) -> Step:
        inv = 1.0 / self.dt
        return Step(np.array(th[:3]), np.array([th[3] * inv, th[4] * inv, th[5] * inv]), predicted=predicted)

    def _start(self, y: np.ndarray) -> bool:
        """Offer this frame to the shared initiator; False while no start is possible."""
        s = self.start(y)
        if s is None:
            return False
        self._begin(s)
        return True

    def _begin(self, s: Start) -> None:
        """θ from a start (frame units inside: ``[p, v·dt]``)."""
        self.theta = [*s.state[:3].tolist(), *(s.state[3:] * self.dt).tolist()]
        self.initialized = True
        self._phase = 0

    def _step(self, y: np.ndarray) -> Step:
        if not self.initialized:
            if not self._start(y):
                return not_started()
            return self._out(self.theta, False)
        th, predicted = self._iterate(*self._normalize(y))
        return self._out(th, predicted)

    def _iterate(self, yn: tuple, ok_l: bool, ok_r: bool) -> tuple[list[float], bool]:
        """One frame of Algorithm 1 on a normalized observation; returns (θ for this frame, gap)."""
        t = self.theta
        b = self._beta
        if self._phase == 0:
            # x_{2k−1} = A(θ − βΔ): position p − βΔp + (v − βΔv)
            D = self._delta = self._draw_delta()
            self._y_odd = (yn, ok_l, ok_r)
            self._trial_odd = (
                t[0] - b * D[0] + t[3] - b * D[3],
                t[1] - b * D[1] + t[4] - b * D[4],
                t[2] - b * D[2] + t[5] - b * D[5],
            )
            self._phase = 1
            return [t[0] + t[3], t[1] + t[4], t[2] + t[5], t[3], t[4], t[5]], not (ok_l or ok_r)  # θ_{2k−1} = Aθ
        self._phase = 0
        D = self._delta
        yo, ol, orr = self._y_odd
        use_l, use_r = ok_l and ol, ok_r and orr
        new = [t[0] + 2 * t[3], t[1] + 2 * t[4], t[2] + 2 * t[5], t[3], t[4], t[5]]  # A²θ
        if use_l or use_r:
            xe = (
                t[0] + b * D[0] + 2 * (t[3] + b * D[3]),
                t[1] + b * D[1] + 2 * (t[4] + b * D[4]),
                t[2] + b * D[2] + 2 * (t[5] + b * D[5]),
            )
            xo = self._trial_odd
            z_odd = _cost(xo[0], xo[1], xo[2], yo, use_l, use_r, self._cams)
            z_even = _cost(xe[0], xe[1], xe[2], yn, use_l, use_r, self._cams)
            d = (z_even - z_odd) / (2 * b)
            th = self._th
            if d > th:
                d = th
            elif d < -th:
                d = -th
            if d == d:  # not NaN
                a = self._alpha * d
                new = [new[0] - a * D[0], new[1] - a * D[1], new[2] - a * D[2],
                       new[3] - a * D[3], new[4] - a * D[4], new[5] - a * D[5]]
        self.theta = new
        return new, not (use_l or use_r)

    def _fast(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every frame from a fresh state through the compiled core (:func:`kernels.spsa_frames`,
        the arithmetic of repeated :meth:`step`): θ per frame (frames × 6, frame units; NaN before
        the start) and which frames only predicted."""
        import pipeline.estimators.compiled as kernels

        self.reset()
        n = len(Y)
        states, pred = np.full((n, 6), np.nan), np.ones(n, dtype=bool)
        start = self.initiator.first(Y)  # the start `step` finds frame by frame, found at once
        if start is not None:
            self._begin(start)
            k = start.frame
            states[k], pred[k] = self.theta, False
            s = kernels.new_state(self.theta)
            deltas = delta_sequence(self.config.seed, n // 2 + 2, 6)
            kernels.spsa_frames(self.rig.normalize(Y[k + 1 :]), *_present(Y[k + 1 :]), deltas, spsa_cameras(self.rig),
                                kernels.SPSAGains(self._alpha, self._beta, self._th), s, states[k + 1 :], pred[k + 1 :])
            self.theta = s.theta.tolist()
        self.frame = n
        return states, pred

    def _loop(self, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`_fast`, through :meth:`_iterate` in one interpreted loop (observations
        normalized at once, states kept as plain lists until the end, no per-frame arrays): the
        arithmetic of repeated :meth:`step`, for clips too short for compiling to pay."""
        self.reset()
        n, d = len(Y), self.state_dim
        rows, okl, okr = normalized_rows(self.rig, Y)
        states: list = [None] * n
        pred = [True] * n
        start = self.initiator.first(Y)
        if start is not None:
            self._begin(start)
            k = start.frame
            states[k], pred[k] = list(self.theta), False
            iterate = self._iterate
            for j in range(k + 1, n):
                states[j], pred[j] = iterate(tuple(rows[j]), okl[j], okr[j])
        self.frame = n
        blank = [math.nan] * d
        return (np.array([s if s is not None else blank for s in states], dtype=float).reshape(n, d),
                np.array(pred, dtype=bool))

    def run(self, Y: np.ndarray) -> Track:
        """The clip through :meth:`_fast` (the kernels compiled or loaded before the timing starts),
        or through :meth:`_loop` where compiling would not pay (:func:`~pipeline.estimators.base.use_compiled`)."""
        Y = self.check(Y)
        frames = self._path(len(Y))
        if frames == self._loop:
            frames(Y[: self.warmup_frames])
        t0 = time.perf_counter()
        states, pred = frames(Y)
        elapsed = time.perf_counter() - t0
        vel = states[:, 3:] / self.dt if self.state_dim == 6 else np.full((len(Y), 3), np.nan)
        return self.make_track(states[:, :3], vel, pred, elapsed / max(len(Y), 1), Y)

    def _path(self, frames: int):
        """:meth:`_fast` (its kernel compiled or loaded here) where compiling pays, else :meth:`_loop`."""
        if not use_compiled(frames):
            return self._loop
        import pipeline.estimators.compiled as kernels

        kernels.warm_up("spsa_frames")
        return self._fast

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """Algorithm 1 over M tracks (M × frames × 4 → M × frames × 3) through the compiled
        :func:`kernels.spsa_batch`: each track starts where the initiator says (as :meth:`run`) and
        draws the same Δ sequence a single track draws."""
        import pipeline.estimators.compiled as kernels

        Y = np.asarray(Y, dtype=float)
        self.reset()
        M, n, _ = Y.shape
        starts = self.initiator.first_batch(Y)
        begin = np.array([s.frame if s is not None else n for s in starts], dtype=np.int64)
        theta0 = np.array([s.state if s is not None else np.zeros(6) for s in starts]).reshape(M, 6)
        theta0[:, 3:] *= self.dt  # frame units: [p, v·dt]
        out = np.full((M, n, 3), np.nan)
        Ks = np.stack([c.K for c in self.rig.cameras]).astype(float)
        kernels.spsa_batch(Y, Ks, begin, theta0, delta_sequence(self.config.seed, n // 2 + 2, 6), spsa_cameras(self.rig),
                           kernels.SPSAGains(self._alpha, self._beta, self._th), kernels.new_state(np.zeros(6)), out)
        return out


def _present(Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Whether each frame has the left and the right camera's observation (…×4 → two …)."""
    ok = np.isfinite(Y)
    return ok[..., 0] & ok[..., 1], ok[..., 2] & ok[..., 3]


def spsa_cameras(rig) -> np.ndarray:
    """Both cameras' ``(R, t)`` as a 2 × 12 array (R row-major, then t) for the compiled cost."""
    return np.array(camera_tuples(rig), dtype=float)
