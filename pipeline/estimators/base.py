"""The estimator protocol shared by every method, and the state-space model they assume.

State model for a moving point (SPEC §4.2, thesis ch. II)::

    x = [p; v] ∈ R⁶,   x_k = A x_{k−1} + w_k,   A = [[I, dt·I], [0, I]]
    y_k = h(x_k) + v_k,   h(x) = [proj(P1, p); proj(P2, p)] ∈ R⁴  (pixels)

Every estimator is built from a pydantic config + the stereo rig + ``dt``; ``step(y)`` consumes one
frame's observation ``[u1, v1, u2, v2]`` (NaN where a camera has no detection) and returns a
:class:`Step`; ``run(Y)`` consumes a whole clip (frames × 4) and returns a :class:`Track`.
Observations are undistorted pixels; estimators never see images or files.
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.camera import StereoRig
from pipeline.errors import StereotrackError


def transition(dt: float, dim: int = 3) -> np.ndarray:
    """Constant-velocity transition ``A = [[I, dt·I], [0, I]]``."""
    A = np.eye(2 * dim)
    A[:dim, dim:] = dt * np.eye(dim)
    return A


def white_noise_acceleration(dt: float, q: float, dim: int = 3) -> np.ndarray:
    """Process noise of a continuous white-noise acceleration of spectral density ``q`` (m²/s³):
    ``Q = q [[dt³/3 I, dt²/2 I], [dt²/2 I, dt I]]`` (Bar-Shalom, Li & Kirubarajan, §6.2.2)."""
    I = np.eye(dim)
    return q * np.block([[dt**3 / 3 * I, dt**2 / 2 * I], [dt**2 / 2 * I, dt * I]])


class InitConfig(BaseModel):
    """How a track starts: from the first triangulation (default) or from a given state."""

    model_config = ConfigDict(extra="forbid")
    mode: Literal["triangulation", "given"] = "triangulation"
    #: the given state [x, y, z, vx, vy, vz] (mode "given")
    state: tuple[float, float, float, float, float, float] | None = None
    #: triangulated frames used to start: 1 = position only (velocity 0); n ≥ 2 fits a straight line
    #: through the first n triangulations (position at the n-th frame, velocity from the fit)
    frames: int = Field(1, ge=1, le=100)
    #: prior std of position (m) and velocity (m/s), used by the Kalman family's P0
    sigma_position: float = Field(0.5, gt=0)
    sigma_velocity: float = Field(1.0, gt=0)


class EstimatorConfig(BaseModel):
    """Settings every estimator accepts."""

    model_config = ConfigDict(extra="forbid")
    init: InitConfig = InitConfig()
    seed: int = 0


@dataclass
class Step:
    """One frame's output: position, velocity (NaN when the method has none) and diagnostics."""

    position: np.ndarray
    velocity: np.ndarray
    reprojection_error: float = float("nan")
    covariance: np.ndarray | None = None
    predicted: bool = False  # no measurement was used this frame (gap)
    extra: dict[str, float] = field(default_factory=dict)


@dataclass
class Track:
    """A whole clip's estimates for one marker (frames × 3) plus per-frame diagnostics."""

    method: str
    position: np.ndarray
    velocity: np.ndarray
    reprojection_error: np.ndarray
    covariance_trace: np.ndarray
    predicted: np.ndarray
    seconds_per_step: float
    extra: dict[str, np.ndarray] = field(default_factory=dict)


NAN3 = np.full(3, np.nan)


class Estimator(ABC):
    """Base class: subclasses implement :meth:`step` (and may vectorise :meth:`run_batch`)."""

    name: ClassVar[str]
    Config: ClassVar[type[EstimatorConfig]] = EstimatorConfig
    #: True for methods that take stereo point observations (False: four-point target methods)
    point_method: ClassVar[bool] = True

    def __init__(self, rig: StereoRig, dt: float, config: EstimatorConfig | dict[str, Any] | None = None) -> None:
        rig.check()
        if not dt > 0:
            raise StereotrackError(f"time step must be positive, got {dt}")
        self.rig = rig
        self.dt = float(dt)
        self.config = self.Config.model_validate(config or {}) if not isinstance(config, self.Config) else config
        self.reset()

    def reset(self) -> None:
        """Forget the track; the next observation starts a new one."""
        self.initialized = False
        self.rng = np.random.default_rng(self.config.seed)
        self._init_buffer: list[np.ndarray] = []

    # -- helpers shared by the point estimators ------------------------------------------------
    def initial_state(self, y: np.ndarray) -> np.ndarray | None:
        """Start state from the config: given, or the triangulation of ``y`` (None if impossible)."""
        init = self.config.init
        if init.mode == "given":
            if init.state is None:
                raise StereotrackError("init.mode 'given' needs init.state")
            return np.array(init.state, dtype=float)
        from pipeline.estimators.triangulation import triangulate

        X = triangulate(self.rig, y[None])[0] if np.all(np.isfinite(y)) else np.full(3, np.nan)
        buf = self._init_buffer
        buf.append(X)
        if not np.all(np.isfinite(X)) or np.any(self.rig.left.depth(X[None]) <= 0):
            if len(buf) > 4 * init.frames:
                buf.pop(0)
            return None
        pts = np.array(buf[-init.frames :])
        if init.frames == 1:
            buf.clear()
            return np.concatenate([X, np.zeros(3)])
        if len(pts) < init.frames or not np.all(np.isfinite(pts)):
            return None
        t = np.arange(init.frames) * self.dt
        slope, _ = np.polyfit(t, pts, 1)
        buf.clear()
        return np.concatenate([X, slope])

    def reprojection_error(self, p: np.ndarray, y: np.ndarray) -> float:
        """RMS pixel distance between ``h(p)`` and the available observations."""
        ok = np.isfinite(y)
        if not ok.any() or not np.all(np.isfinite(p)):
            return float("nan")
        r = self.rig.project(p[None])[0] - y
        return float(np.sqrt(np.mean(r[ok] ** 2)))

    # -- the protocol ---------------------------------------------------------------------------
    @abstractmethod
    def _step(self, y: np.ndarray) -> Step:
        """The numerical core of :meth:`step`, without diagnostics that :meth:`run` vectorises."""

    def step(self, y: np.ndarray) -> Step:
        """Consume one frame's observation ``[u1, v1, u2, v2]`` (NaN = missing)."""
        s = self._step(np.asarray(y, dtype=float))
        s.reprojection_error = self.reprojection_error(s.position, y)
        return s

    def run(self, Y: np.ndarray) -> Track:
        """Run over a clip's observations (frames × 4) from a fresh state."""
        Y = check_observations(Y)
        self.reset()
        n = len(Y)
        pos, vel = np.full((n, 3), np.nan), np.full((n, 3), np.nan)
        ctr = np.full(n, np.nan)
        pred = np.zeros(n, dtype=bool)
        extra: dict[str, np.ndarray] = {}
        t0 = time.perf_counter()
        for k in range(n):
            s = self._step(Y[k])
            pos[k], vel[k], pred[k] = s.position, s.velocity, s.predicted
            if s.covariance is not None:
                ctr[k] = float(np.trace(s.covariance))
            for key, val in s.extra.items():
                extra.setdefault(key, np.full(n, np.nan))[k] = val
        elapsed = time.perf_counter() - t0
        rep = reprojection_errors(self.rig, pos, Y)
        return Track(self.name, pos, vel, rep, ctr, pred, elapsed / max(n, 1), extra)

    def run_batch(self, Y: np.ndarray) -> np.ndarray:
        """Positions for many tracks at once (tracks × frames × 4 → tracks × frames × 3).

        The base version loops over tracks; methods with a vectorised core override it.
        """
        return np.stack([self.run(y).position for y in Y])


def reprojection_errors(rig: StereoRig, positions: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Per-frame RMS pixel distance between ``h(position)`` and the available observations."""
    ok = np.all(np.isfinite(positions), axis=1)
    r = np.full(Y.shape, np.nan)
    r[ok] = rig.project(positions[ok]) - Y[ok]
    with np.errstate(invalid="ignore"):
        n = np.sum(np.isfinite(r), axis=1)
        out = np.sqrt(np.nansum(r**2, axis=1) / np.maximum(n, 1))
    out[n == 0] = np.nan
    return out


def check_observations(Y: np.ndarray, source: str = "observations") -> np.ndarray:
    """Validate an observation array (frames × 4): NaN marks a missing camera, inf is an error."""
    Y = np.asarray(Y, dtype=float)
    if Y.ndim != 2 or Y.shape[1] != 4:
        raise StereotrackError(f"{source}: expected frames × 4 observations [u1, v1, u2, v2], got shape {Y.shape}")
    if np.isinf(Y).any():
        raise StereotrackError(f"{source}: infinite pixel coordinates")
    return Y


REGISTRY: dict[str, type[Estimator]] = {}


def register(cls: type[Estimator]) -> type[Estimator]:
    """Class decorator: make an estimator available by name to the pipeline, CLI and benchmarks."""
    REGISTRY[cls.name] = cls
    return cls
