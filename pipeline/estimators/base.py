"""The one estimator protocol, the one track initiator and the one registry.

State model for a moving point (Krivokon 2011, ch. II)::

    x = [p; v] ∈ R⁶,   x_k = A x_{k−1} + w_k,   A = [[I, dt·I], [0, I]]
    y_k = h(x_k) + v_k,   h(x) = [proj(P1, p); proj(P2, p)] ∈ R⁴  (pixels)

with ``h`` the :class:`pipeline.core.camera.StereoMeasurementModel` of the rig. Every method — point
and four-point target alike — is built from a pydantic config + the stereo rig + ``dt`` and has
three equivalent paths that give the same numbers (tested):

- ``step(obs)``: one frame (streaming), then ``finish(steps, Y)`` for the whole track (smoothed there);
- ``run(Y)``: a clip — ``reset``, ``step`` every frame, ``finish``;
- ``run_batch(Ys)``: many tracks at once (vectorised where a method can be).

Observations are undistorted pixels, NaN where a camera has no detection: ``[u1, v1, u2, v2]`` for
point methods, 4 points × 4 for four-point target methods. Estimators never see images or files.
Methods register with :func:`register`; third-party packages add theirs through the entry-point
group ``stereotrack.estimators`` (see :func:`registry`).
"""

from __future__ import annotations

import functools
import time
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from pipeline.core import linalg
from pipeline.core.camera import StereoMeasurementModel, StereoRig
from pipeline.core.errors import StereotrackError
from pipeline.core.rig import Rig
from pipeline.estimators.gating import plausible_residual, plausible_triangulation, reprojection_errors

Kind = Literal["point", "target"]


def expm(M: np.ndarray) -> np.ndarray:
    """``scipy.linalg.expm`` (:func:`pipeline.core.linalg.expm`, the same bits without importing
    scipy.linalg), remembered: the continuous-time filters exponentiate the same few matrices every
    frame (same model, same dt), so each is computed once. Read-only result."""
    M = np.ascontiguousarray(M, dtype=float)
    return _expm(M.tobytes(), M.shape)


@functools.lru_cache(maxsize=256)
def _expm(data: bytes, shape: tuple[int, ...]) -> np.ndarray:
    E = linalg.expm(np.frombuffer(data).reshape(shape))
    E.flags.writeable = False
    return E


#: clips shorter than this run a compiled method's interpreted loop (the same numbers, tested),
#: unless the compiled cores are loaded already: loading numba and the cached kernels costs a
#: fresh process about half a second, which the compiled EKF earns back only over ~10,000 steps
JIT_MIN_FRAMES = 1000


def use_compiled(frames: int) -> bool:
    """Whether a ``run`` over ``frames`` frames goes through the compiled cores
    (:mod:`pipeline.estimators.compiled`): long clips, or any clip once the cores are loaded."""
    import sys

    return frames >= JIT_MIN_FRAMES or "pipeline.estimators.compiled" in sys.modules


def transition(dt: float, dim: int = 3) -> np.ndarray:
    """Constant-velocity transition ``A = [[I, dt·I], [0, I]]``."""
    A = np.eye(2 * dim)
    A[:dim, dim:] = dt * np.eye(dim)
    return A


def white_noise_acceleration(dt: float, q: float, dim: int = 3) -> np.ndarray:
    """Process noise of a continuous white-noise acceleration of spectral density ``q`` (m²/s³),
    ``Q = q [[dt³/3 I, dt²/2 I], [dt²/2 I, dt I]]`` (Bar-Shalom, Li & Kirubarajan §6.2.2): filterpy's
    ``Q_continuous_white_noise`` in our ``[p; v]`` state order (tested equal)."""
    return np.kron(np.array([[dt**3 / 3.0, dt**2 / 2.0], [dt**2 / 2.0, dt]]), np.eye(dim)) * q


class InitConfig(BaseModel):
    """How a track starts (:class:`Initiator`): from triangulations or from a given state."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, defer_build=True)  # built when first validated
    mode: Literal["triangulation", "given"] = "triangulation"
    """'triangulation': start from the first frames both cameras see; 'given': from ``state``"""
    state: tuple[float, float, float, float, float, float] | None = None
    """the given state [x, y, z, vx, vy, vz] at frame 0 (mode "given")"""
    frames: int = Field(1, ge=1, le=100)
    """frames with both cameras used to start: 1 = position only (velocity 0); n ≥ 2 fits a straight line through the first
    n such frames (they need not be consecutive)"""
    sigma_position: float = Field(0.5, gt=0)
    """prior std of position (m) and velocity (m/s); the position prior of methods that know their pixel noise is the
    triangulation's own covariance instead"""
    sigma_velocity: float = Field(1.0, gt=0)
    """prior std of the start's velocity (m/s)"""

    @model_validator(mode="after")
    def _given_needs_state(self) -> InitConfig:
        if self.mode == "given" and self.state is None:
            raise ValueError("init.mode 'given' needs init.state [x, y, z, vx, vy, vz]")
        return self


class EstimatorConfig(BaseModel):
    """Settings every estimator accepts (numbers must be finite: ``.inf`` is no setting)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, defer_build=True)  # built when first validated
    init: InitConfig = Field(default_factory=InitConfig)
    """how a track starts: ``mode``, ``state``, ``frames``, ``sigma_position``, ``sigma_velocity``"""
    seed: int = 0
    """seed of the method's random numbers (SPSA's perturbations): one seed, one result"""
    pixel_sigma: float = Field(1.0, gt=0)
    """std (px) of detection noise: the scale of the outlier gate, and the measurement noise of the methods that model it
    (the pipeline sets it from the data unless configured)"""
    gate: float = Field(0.9995, ge=0.0, lt=1.0)
    """probability of the χ² outlier gate (per camera, 2 degrees of freedom, on the innovation); 0 turns gating off. 0.9995
    rejects a correct observation once in 2,000."""
    restart_after: int = Field(8, ge=1)
    """frames in a row with a camera's observation gated after which a track restarts from the detections"""


@dataclass
class Step:
    """One frame's output: position, velocity (NaN when the method has none), the state covariance,
    the innovation ``y`` and its covariance ``S`` (filterpy's names) when a filter updated, and
    method-specific values in ``extra``."""

    position: np.ndarray
    velocity: np.ndarray
    predicted: bool = False  # no measurement was used this frame (gap, or not started)
    covariance: np.ndarray | None = None
    innovation: np.ndarray | None = None
    innovation_covariance: np.ndarray | None = None
    extra: dict[str, float] = field(default_factory=dict)
    #: ``yᵀ S⁻¹ y`` when the filter already has ``S⁻¹`` (saves solving again in :attr:`nis`)
    known_nis: float | None = None

    @property
    def nis(self) -> float:
        """Normalized innovation squared ``yᵀ S⁻¹ y`` (NaN without an update)."""
        if self.innovation is None or self.innovation_covariance is None:
            return float("nan")
        if self.known_nis is not None:
            return self.known_nis
        y = np.ravel(self.innovation)
        return float(y @ np.linalg.solve(self.innovation_covariance, y))


@dataclass
class Track:
    """A whole clip's estimates for one marker (frames × 3) plus per-frame diagnostics.

    ``covariance``: frames × d × d state covariances (NaN before the start; None for methods
    without one); ``nis``/``nis_dof``: the normalized innovation squared and its degrees of freedom
    (NaN/0 on frames without an update).
    """

    method: str
    position: np.ndarray
    velocity: np.ndarray
    reprojection_error: np.ndarray
    predicted: np.ndarray
    seconds_per_step: float
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    covariance: np.ndarray | None = None
    nis: np.ndarray | None = None
    nis_dof: np.ndarray | None = None


NAN3 = np.full(3, np.nan)


# -- the initiator ------------------------------------------------------------------------------
@dataclass
class Start:
    """Where a track starts: the frame, the state ``[p; v]`` at that frame and its covariance."""

    frame: int
    state: np.ndarray
    covariance: np.ndarray


class Initiator:
    """The one way every point method starts a track (streaming :meth:`offer`, or :meth:`first`
    over a whole clip — the same arithmetic).

    - ``given``: the configured state at frame 0, covariance ``diag(σp², σv²)``;
    - ``triangulation`` with ``frames = 1``: the first frame whose triangulation (the model's
      ``inverse_function``) is finite and in front of both cameras; velocity 0;
    - ``frames = n ≥ 2``: a least-squares line ``p(t) = p + v t`` through the first n such frames
      (t relative to the n-th), starting at the n-th with ``[p; v]``. With ``C`` the covariance of
      one triangulation and ``t̄, Sₜₜ`` the mean and spread of the times, the line's covariance is
      ``Var p = C (1/n + t̄²/Sₜₜ)``, ``Var v = C / Sₜₜ``, ``Cov(p, v) = −C t̄ / Sₜₜ``.

    ``C`` is ``σ² (JᵀJ)⁻¹`` (the model's ``inverse_covariance``) when ``propagate`` is set — for
    methods that know their pixel noise — else ``σp² I``.
    """

    def __init__(self, config: InitConfig, model: StereoMeasurementModel, dt: float, propagate: bool = False,
                 gate: float = 0.0) -> None:
        self.config, self.model, self.dt, self.propagate = config, model, float(dt), propagate
        #: largest plausible sum of squared reprojection residuals (px²) of a triangulation
        self.max_residual = plausible_residual(model.pixel_sigma, gate)
        self.reset()

    def reset(self) -> None:
        self._frames: list[int] = []
        self._points: list[np.ndarray] = []

    def _valid(self, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
        """Triangulations in front of both cameras whose reprojection is plausible (an outlier in
        one camera off the epipolar line leaves a residual no detection noise explains)."""
        return plausible_triangulation(self.model, X, Y, self.max_residual)

    def _given(self, frame: int) -> Start:
        c = self.config
        P0 = np.diag(np.r_[np.full(3, c.sigma_position**2), np.full(3, c.sigma_velocity**2)])
        return Start(frame, np.array(c.state, dtype=float), P0)

    def _fit(self, frames: np.ndarray, points: np.ndarray) -> Start:
        """The start from one track's frames and triangulated points (:meth:`_fit_many` of one)."""
        states, covs = self._fit_many(np.asarray(frames)[None], np.asarray(points)[None])
        return Start(int(frames[-1]), states[0], covs[0])

    def _fit_many(self, frames: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The starts of M tracks at once (``frames`` M × n, ``points`` M × n × 3): states M × 6
        and covariances M × 6 × 6, at each track's last frame."""
        c = self.config
        M, n = frames.shape
        C = (self.model.inverse_covariance(points[:, -1]) if self.propagate
             else np.broadcast_to(np.eye(3) * c.sigma_position**2, (M, 3, 3)))
        P0, x0 = np.zeros((M, 6, 6)), np.zeros((M, 6))
        if n == 1:
            P0[:, :3, :3], P0[:, 3:, 3:] = C, np.eye(3) * c.sigma_velocity**2
            x0[:, :3] = points[:, -1]
            return x0, P0
        t = (frames - frames[:, -1:]) * self.dt
        tm = t.mean(axis=1)
        stt = np.sum((t - tm[:, None]) ** 2, axis=1)
        v = np.einsum("mn,mnj->mj", t - tm[:, None], points - points.mean(axis=1, keepdims=True)) / stt[:, None]
        x0[:, :3], x0[:, 3:] = points.mean(axis=1) - v * tm[:, None], v
        P0[:, :3, :3] = C * (1.0 / n + tm**2 / stt)[:, None, None]
        P0[:, 3:, 3:] = C / stt[:, None, None]
        P0[:, :3, 3:] = P0[:, 3:, :3] = -C * (tm / stt)[:, None, None]
        return x0, P0

    def offer(self, frame: int, y: np.ndarray) -> Start | None:
        """Consume frame ``frame``'s observation; the start once enough frames were seen."""
        if self.config.mode == "given":
            return self._given(frame)
        y = np.asarray(y, dtype=float)
        X = self.model.inverse_function(y[None])[0]
        if not self._valid(X, y):
            return None
        self._frames.append(frame)
        self._points.append(X)
        if len(self._frames) < self.config.frames:
            return None
        return self._fit(np.array(self._frames), np.array(self._points))

    def restart(self, frame: int, recent: np.ndarray) -> Start | None:
        """A new start for a track gated for too long, from its recent detections alone (``recent``:
        the observations of the frames up to and including ``frame``, oldest first): a line through
        the plausible triangulations among them, so the new track starts with the velocity of what it
        now follows; None when this frame's detections do not triangulate plausibly."""
        Y = np.asarray(recent, dtype=float).reshape(-1, self.model.ndim_meas)
        X = self.model.inverse_function(Y)
        ok = self._valid(X, Y)
        if not ok[-1]:
            return None
        frames = frame - len(Y) + 1 + np.arange(len(Y))
        return self._fit(frames[ok], X[ok])

    def first(self, Y: np.ndarray) -> Start | None:
        """The start over a whole clip's observations (frames × 4); None if it never starts."""
        return self.first_batch(np.asarray(Y, dtype=float)[None])[0]

    def first_batch(self, Y: np.ndarray) -> list[Start | None]:
        """The start of each of M clips (M × frames × 4). Frames are triangulated in chunks from
        the front, only for the tracks that have not started yet (a batch needs the first few
        frames of each track, not all of them)."""
        M, n = Y.shape[:2]
        if self.config.mode == "given":
            return [self._given(0) if n else None for _ in range(M)]
        need = self.config.frames
        got, F, pts = np.zeros(M, dtype=int), np.zeros((M, need), dtype=int), np.zeros((M, need, 3))
        todo = np.arange(M)
        lo, chunk = 0, need
        while len(todo) and lo < n:
            hi = min(n, lo + chunk)
            X = self.model.inverse_function(Y[todo, lo:hi])
            valid = self._valid(X, Y[todo, lo:hi])
            slot = got[todo][:, None] + np.cumsum(valid, axis=1) - 1  # where each valid frame goes
            i, k = np.nonzero(valid & (slot < need))
            F[todo[i], slot[i, k]], pts[todo[i], slot[i, k]] = lo + k, X[i, k]
            got[todo] = np.minimum(got[todo] + valid.sum(axis=1), need)
            todo, lo, chunk = todo[got[todo] < need], hi, 2 * chunk
        done = np.flatnonzero(got == need)
        out: list[Start | None] = [None] * M
        if not len(done):  # no track starts (a clip shorter than the start needs: the warm-up's frames)
            return out
        states, covs = self._fit_many(F[done], pts[done])
        for j, m in enumerate(done):
            out[m] = Start(int(F[m, -1]), states[j], covs[j])
        return out


# -- the protocol -------------------------------------------------------------------------------
class Estimator(ABC):
    """Base of every method: subclasses implement :meth:`_step`; smoothers override :meth:`finish`;
    methods with a vectorised core override :meth:`run_batch` (tested equal to :meth:`run`)."""

    name: ClassVar[str]
    #: "point": observations [u1, v1, u2, v2]; "target": 4 points × [u1, v1, u2, v2]
    kind: ClassVar[Kind] = "point"
    Config: ClassVar[type[EstimatorConfig]] = EstimatorConfig
    #: frames stepped (then forgotten) before the timed loop of :meth:`run`, so that one-off
    #: start-up (imports, first allocations) is not counted as time per step
    warmup_frames: ClassVar[int] = 3
    #: the fewest frames of a clip on which the method gives an estimate (SPSA pairs consecutive
    #: frames); on a shorter clip ``metrics.json`` and the report say so instead of an error
    min_frames: ClassVar[int] = 1

    #: whether the method places the right camera's observation at its own time through the
    #: measurement model (a state with velocity); the others are given the right camera's
    #: detections interpolated to the left camera's times when the cameras are out of sync
    models_time_offset: ClassVar[bool] = False
    #: whether a target method takes the rendered target's dynamics (its ``config``) as settings
    models_target_dynamics: ClassVar[bool] = False
    #: whether the method takes a :class:`~pipeline.core.camera.Rig` of any number of cameras (its
    #: observations 2N wide); the others take a two-camera :class:`StereoRig`
    any_cameras: ClassVar[bool] = False
    #: whether ``estimate`` runs the method when ``--methods`` does not name it (False: an option
    #: for one kind of motion, run when asked)
    default: ClassVar[bool] = True
    #: modules the method imports when it first runs that take long to import (``estimate`` runs
    #: the methods sharing one in one process, so that it is imported once)
    startup_imports: ClassVar[tuple[str, ...]] = ()

    def __init__(self, rig: StereoRig | Rig, dt: float, config: EstimatorConfig | dict[str, Any] | None = None,
                 time_offset: float = 0.0) -> None:
        rig.check()
        if not (self.any_cameras or isinstance(rig, StereoRig)):
            raise StereotrackError(f"{self.name} takes a stereo pair; with {rig.n} cameras use one of "
                                   f"{', '.join(n_camera_methods())}")
        if not dt > 0:
            raise StereotrackError(f"time step must be positive, got {dt}")
        self.rig = rig
        self.dt = float(dt)
        self.config = config if isinstance(config, self.Config) else self.Config.model_validate(config or {})
        sigma = float(getattr(self.config, "pixel_sigma", 1.0))
        self.model = StereoMeasurementModel(rig, sigma, time_offset=float(time_offset) if self.models_time_offset else 0.0)
        self.reset()

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        if cls.__dict__.get("any_cameras", cls.any_cameras) and "name" in cls.__dict__:
            _N_CAMERA_METHODS.add(cls.name)

    @classmethod
    def description(cls) -> str:
        """One line: the first line of the class docstring."""
        return (cls.__doc__ or "").strip().splitlines()[0] if cls.__doc__ else ""

    @classmethod
    def knows_pixel_noise(cls) -> bool:
        """Whether the config has a ``pixel_sigma`` (the pipeline fills it from the data)."""
        return "pixel_sigma" in cls.Config.model_fields

    def reset(self) -> None:
        """Forget the track; the next observation starts a new one."""
        self.initialized = False
        self.frame = 0
        self.rng = np.random.default_rng(self.config.seed)
        self.initiator = Initiator(self.config.init, self.model, self.dt, propagate=self.knows_pixel_noise(),
                                   gate=self.config.gate)
        self.gated_run: int = 0  # frames in a row with a camera gated
        self.unseen: list[int] = [0] * self.model.rig.n  # per camera: frames since it last observed
        self.returning: int = 0  # frames back from a long gap
        self.recent: deque = deque(maxlen=self.config.restart_after)  # what a restart fits

    def start(self, y: np.ndarray) -> Start | None:
        """Offer this frame to the initiator (point methods)."""
        return self.initiator.offer(self.frame, y)

    def reprojection_error(self, p: np.ndarray, y: np.ndarray) -> float:
        """RMS pixel distance between ``h(p)`` and the available observations."""
        return float(reprojection_errors(self.rig, np.asarray(p, float)[None], np.asarray(y, float)[None])[0])

    @abstractmethod
    def _step(self, obs: np.ndarray) -> Step:
        """The numerical core of :meth:`step`."""

    def step(self, obs: np.ndarray) -> Step:
        """Consume one frame's observation (NaN = missing) and return this frame's estimate."""
        y = np.asarray(obs, dtype=float)
        self.recent.append(y)
        s = self._step(y)
        self.frame += 1
        return s

    def recent_observations(self) -> np.ndarray:
        """The last ``restart_after`` observations, this frame's last (what a restart fits)."""
        return np.array(self.recent)

    def check(self, Y: np.ndarray, source: str = "observations") -> np.ndarray:
        """Validate a clip's observations for this method's kind (NaN = missing, inf = error)."""
        Y = np.asarray(Y, dtype=float)
        m = self.model.ndim_meas
        want = (m,) if self.kind == "point" else (4, m)
        if Y.ndim != 1 + len(want) or Y.shape[1:] != want:
            what = (f"frames × {m} observations [u1, v1, u2, v2, …]" if self.kind == "point"
                    else f"frames × 4 points × {m}")
            raise StereotrackError(f"{source}: expected {what}, got shape {Y.shape}")
        if np.isinf(Y).any():
            raise StereotrackError(f"{source}: infinite pixel coordinates")
        return Y

    def finish(self, steps: list[Step], Y: np.ndarray, seconds_per_step: float = float("nan")) -> Track:
        """The track of a clip from its steps (a smoother's backward pass goes here)."""
        n = len(steps)
        pos = np.array([s.position for s in steps], dtype=float).reshape(n, 3)
        vel = np.array([s.velocity for s in steps], dtype=float).reshape(n, 3)
        pred = np.array([s.predicted for s in steps], dtype=bool)
        covs = [s.covariance for s in steps]
        cov = None
        d = next((c.shape[0] for c in covs if c is not None), None)
        if d is not None:
            cov = np.full((n, d, d), np.nan)
            for k, c in enumerate(covs):
                if c is not None:
                    cov[k] = c
        nis = np.array([s.nis for s in steps], dtype=float)
        dof = np.array([0 if s.innovation is None else np.size(s.innovation) for s in steps], dtype=int)
        extra: dict[str, np.ndarray] = {}
        for k, s in enumerate(steps):
            for key, val in s.extra.items():
                extra.setdefault(key, np.full(n, np.nan))[k] = val
        return self.make_track(pos, vel, pred, seconds_per_step, Y, extra, cov,
                               nis if dof.any() else None, dof if dof.any() else None)

    def make_track(self, position: np.ndarray, velocity: np.ndarray, predicted: np.ndarray, seconds_per_step: float,
                   Y: np.ndarray, extra: dict[str, np.ndarray] | None = None, covariance: np.ndarray | None = None,
                   nis: np.ndarray | None = None, nis_dof: np.ndarray | None = None) -> Track:
        """A :class:`Track` from per-frame arrays, its reprojection errors against ``Y`` computed
        here: the one place a track is made, for :meth:`finish` and for fast paths that never
        build :class:`Step` objects (SPSA, ``spsa_stereo``)."""
        n = len(position)
        rep = (reprojection_errors(self.rig, position, Y, velocity, self.model.time_offset) if self.kind == "point"
               else np.full(n, np.nan))
        return self.complete(Track(self.name, position, velocity, rep, np.asarray(predicted, dtype=bool), seconds_per_step,
                                   extra or {}, covariance, nis, nis_dof), Y)

    def complete(self, track: Track, Y: np.ndarray) -> Track:
        """The last word on a finished track, whichever path made it (step by step or a compiled
        core): a smoother's backward pass goes here. The filter's track as it is by default."""
        return track

    def _timed_steps(self, Y: np.ndarray) -> tuple[list[Step], float]:
        """Warm up on the first frames, then reset and step every frame; (steps, seconds/step)."""
        self.reset()
        for y in Y[: self.warmup_frames]:
            self.step(y)
        self.reset()
        t0 = time.perf_counter()
        steps = [self.step(y) for y in Y]
        return steps, (time.perf_counter() - t0) / max(len(Y), 1)

    def run(self, Y: np.ndarray) -> Track:
        """A clip's observations from a fresh state: ``reset``, ``step`` every frame, ``finish``."""
        Y = self.check(Y)
        steps, sec = self._timed_steps(Y)
        return self.finish(steps, Y, sec)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """Positions of many tracks (tracks × frames × obs → tracks × frames × 3), each from a fresh
        state. This version loops over :meth:`run`; vectorised cores override it."""
        return np.stack([self.run(y).position for y in np.asarray(Y, dtype=float)])


_N_CAMERA_METHODS: set[str] = set()


def n_camera_methods() -> list[str]:
    """The methods (every class defined so far) that take a rig of any number of cameras."""
    return sorted(_N_CAMERA_METHODS)


def not_started() -> Step:
    """The output of a frame before the track has started."""
    return Step(NAN3.copy(), NAN3.copy(), predicted=True)


