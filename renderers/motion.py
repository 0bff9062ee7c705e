"""Ground-truth motion: per-frame 3-D positions and velocities of every marker of a scenario.

Pure numpy and seeded (``numpy.random.default_rng([seed, object_index])``), so the same scenario
and seed give identical truth, bit for bit, whether or not anything is rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.core.linalg import expm
from renderers.scenario import (
    ConstantAcceleration,
    ConstantVelocity,
    FourPointTarget,
    ObjectSpec,
    Scenario,
    Sinusoid,
)


@dataclass
class TargetTruth:
    """Four-point target state per frame (``target_truth.csv``)."""

    name: str
    alpha: np.ndarray
    alpha_dot: np.ndarray
    distance: np.ndarray
    distance_dot: np.ndarray
    axis_angle: float
    radius: float
    #: plate normal (towards the camera side) per frame, N×3
    normal: np.ndarray
    #: plate centre per frame, N×3
    center: np.ndarray


class PointPath:
    """One point motion at any time: exact for the analytic motions; for a constant velocity with
    process noise, the simulated piecewise-constant acceleration between frames (so the frame
    samples are the recursion's own values and in between is exact for that model)."""

    def __init__(self, motion, dt: float, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray | None = None) -> None:
        self.motion, self.dt, self.pos, self.vel, self.acc = motion, dt, pos, vel, acc

    def at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t, dtype=float))
        m = self.motion
        if self.acc is not None:  # noisy constant velocity: quadratic between frames
            k = np.clip(np.floor(t / self.dt).astype(int), 0, len(self.pos) - 1)
            tau = (t - k * self.dt)[:, None]
            return self.pos[k] + self.vel[k] * tau + 0.5 * self.acc[k] * tau**2, self.vel[k] + self.acc[k] * tau
        return _analytic(m, t)


def _analytic(m, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(m, ConstantVelocity):
        p0, v0 = np.array(m.start, float), np.array(m.velocity, float)
        return p0 + np.outer(t, v0), np.tile(v0, (len(t), 1))
    if isinstance(m, ConstantAcceleration):
        p0, v0, a0 = (np.array(x, float) for x in (m.start, m.velocity, m.acceleration))
        return p0 + np.outer(t, v0) + 0.5 * np.outer(t * t, a0), v0 + np.outer(t, a0)
    if isinstance(m, Sinusoid):
        c, amp, ph = (np.array(x, float) for x in (m.center, m.amplitude, m.phase))
        w = 2 * math.pi * np.broadcast_to(np.array(m.frequency_hz, float), (3,))
        arg = np.outer(t, w) + ph
        return c + amp * np.sin(arg), amp * w * np.cos(arg)
    raise TypeError(f"not a point motion: {type(m).__name__}")


class TargetPath:
    """The four-point target at any time: between frames the state ``[α, α̇]`` (and ``[z, ż]``)
    evolves by ``expm(A τ)`` from the frame's state, exactly as the simulation integrates it."""

    def __init__(self, motion: FourPointTarget, dt: float, al: np.ndarray, zz: np.ndarray) -> None:
        self.m, self.dt, self.al, self.zz = motion, dt, al, zz
        self.A_alpha = np.array(motion.alpha_matrix, float)
        self.A_z = np.array([[0.0, 1.0], [0.0, motion.a_z]])

    def state_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(α, α̇) and (z, ż) at times ``t`` (each N×2)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        k = np.clip(np.floor(t / self.dt).astype(int), 0, len(self.al) - 1)
        tau = t - k * self.dt
        al, zz = np.empty((len(t), 2)), np.empty((len(t), 2))
        for i, (kk, tt) in enumerate(zip(k, tau, strict=True)):
            al[i] = expm(self.A_alpha * tt) @ self.al[kk] if tt else self.al[kk]
            zz[i] = expm(self.A_z * tt) @ self.zz[kk] if tt else self.zz[kk]
        return al, zz

    def center(self, zz: np.ndarray) -> np.ndarray:
        m = self.m
        return np.column_stack([np.full(len(zz), m.center_offset[0]), np.full(len(zz), m.center_offset[1]), zz[:, 0]])

    def points_at(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Points (N×4×3), their velocities, the plate normal (N×3), centre (N×3) and α (N)."""
        al, zz = self.state_at(t)
        center = self.center(zz)
        phi = math.radians(self.m.axis_angle_deg)
        pts, normal = target_points(center, al[:, 0], self.m.radius, phi)
        eps = 1e-6
        pts_a, _ = target_points(center, al[:, 0] + eps, self.m.radius, phi)
        vel = (pts_a - pts) / eps * al[:, 1, None, None] + np.array([0.0, 0.0, 1.0]) * zz[:, 1, None, None]
        return pts, vel, normal, center, al[:, 0]


@dataclass
class Truth:
    """Per-frame truth of all markers: ``positions``/``velocities`` are frames × markers × 3;
    :meth:`at` gives the same at any times (sub-frame exposures, sync offsets, rolling shutter)."""

    t: np.ndarray
    names: list[str]
    positions: np.ndarray
    velocities: np.ndarray
    radii: np.ndarray
    #: per marker: unit normal of a flat (disc) marker per frame, or NaN for spheres (frames×markers×3)
    normals: np.ndarray
    targets: list[TargetTruth]
    #: per marker: a PointPath, or (TargetPath, point index 0..3)
    paths: list = field(default_factory=list)
    target_paths: list = field(default_factory=list)

    @property
    def n_frames(self) -> int:
        return len(self.t)

    def at(self, t: np.ndarray, markers: list[int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and normals (NaN for spheres) of ``markers`` (default all) at
        times ``t``: each N×M×3."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        idx = range(len(self.names)) if markers is None else markers
        pos, vel, nrm = (np.full((len(t), len(idx), 3), np.nan) for _ in range(3))
        cache: dict[int, tuple] = {}
        for j, i in enumerate(idx):
            path = self.paths[i]
            if isinstance(path, PointPath):
                pos[:, j], vel[:, j] = path.at(t)
            else:
                tp, q = path
                if id(tp) not in cache:
                    cache[id(tp)] = tp.points_at(t)
                pts, v, n, _, _ = cache[id(tp)]
                pos[:, j], vel[:, j], nrm[:, j] = pts[:, q], v[:, q], n
        return pos, vel, nrm


def target_rotation(axis_angle: float) -> np.ndarray:
    """In-image rotation of the target frame about the optical axis by ``axis_angle`` (rad)."""
    c, s = math.cos(axis_angle), math.sin(axis_angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def target_points(center: np.ndarray, alpha: np.ndarray, radius: float, axis_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The four target points (frames × 4 × 3) and the plate normal (frames × 3).

    Numbering (Soifer, Fursov & Kharitonov): 2 and 4 lie on the rotation axis ``b`` (image x for ``axis_angle = 0``),
    1 and 3 on the in-plane axis ``a`` that turns by α: ``a = (0, −cos α, sin α)`` before the
    in-image rotation, so point 1 (upper) recedes as α grows and point 3 approaches. The plate
    normal faces the camera (``−z`` at α = 0).
    """
    alpha = np.asarray(alpha, dtype=float)
    Rz = target_rotation(axis_angle)
    zeros = np.zeros_like(alpha)
    a = np.stack([zeros, -np.cos(alpha), np.sin(alpha)], -1) @ Rz.T
    b = np.broadcast_to(Rz @ np.array([1.0, 0.0, 0.0]), a.shape)
    n = np.stack([zeros, -np.sin(alpha), -np.cos(alpha)], -1) @ Rz.T
    c = np.asarray(center, dtype=float)
    pts = np.stack([c + radius * a, c + radius * b, c - radius * a, c - radius * b], axis=-2)
    return pts, n


def _second_order(A: np.ndarray, x0: np.ndarray, noise: float, n: int, dt: float, rng: np.random.Generator) -> np.ndarray:
    """Integrate ``ẋ = A x + [0, q]`` exactly between frames (``expm(A dt)``), white noise on the rate."""
    F = expm(A * dt)
    out = np.empty((n, 2))
    x = np.asarray(x0, dtype=float)
    for k in range(n):
        out[k] = x
        x = F @ x
        if noise > 0:
            x = x + np.array([0.0, noise * math.sqrt(dt) * rng.standard_normal()])
    return out


def _point_motion(obj: ObjectSpec, t: np.ndarray, dt: float, rng: np.random.Generator) -> tuple[np.ndarray, ...]:
    """Per-frame position and velocity (and, for a noisy constant velocity, each frame's
    acceleration)."""
    m = obj.motion
    n = len(t)
    if isinstance(m, ConstantVelocity) and m.process_noise > 0:
        p0, v0 = np.array(m.start, float), np.array(m.velocity, float)
        pos, vel = np.empty((n, 3)), np.empty((n, 3))
        p, v = p0, v0
        acc = rng.standard_normal((n, 3)) * m.process_noise
        for k in range(n):
            pos[k], vel[k] = p, v
            p = p + v * dt + 0.5 * acc[k] * dt * dt
            v = v + acc[k] * dt
        return pos, vel, acc
    return _analytic(m, t)


def simulate_truth(scenario: Scenario) -> Truth:
    """Positions and velocities of every marker at every frame of ``scenario``."""
    n, dt = scenario.frames, scenario.dt
    t = np.arange(n) * dt
    names: list[str] = []
    pos_list, vel_list, rad_list, nrm_list = [], [], [], []
    targets: list[TargetTruth] = []
    paths: list = []
    target_paths: list[TargetPath] = []
    for idx, obj in enumerate(scenario.objects):
        rng = np.random.default_rng([scenario.seed, idx])
        m = obj.motion
        if isinstance(m, FourPointTarget):
            al = _second_order(np.array(m.alpha_matrix, float), np.array([m.alpha0, m.alpha_rate0]), m.alpha_noise, n, dt, rng)
            Az = np.array([[0.0, 1.0], [0.0, m.a_z]])
            zz = _second_order(Az, np.array([m.distance0, m.distance_rate0]), m.distance_noise, n, dt, rng)
            center = np.column_stack([np.full(n, m.center_offset[0]), np.full(n, m.center_offset[1]), zz[:, 0]])
            phi = math.radians(m.axis_angle_deg)
            pts, normal = target_points(center, al[:, 0], m.radius, phi)
            # velocities by the chain rule: d/dt of the points wrt alpha and z
            eps = 1e-6
            pts_a, _ = target_points(center, al[:, 0] + eps, m.radius, phi)
            dp_da = (pts_a - pts) / eps
            vel = dp_da * al[:, 1, None, None] + np.array([0.0, 0.0, 1.0]) * zz[:, 1, None, None]
            for j in range(4):
                names.append(obj.marker_names()[j])
                pos_list.append(pts[:, j])
                vel_list.append(vel[:, j])
                rad_list.append(obj.radius)
                nrm_list.append(normal)
            targets.append(
                TargetTruth(obj.name, al[:, 0], al[:, 1], zz[:, 0], zz[:, 1], phi, m.radius, normal, center)
            )
            tp = TargetPath(m, dt, al, zz)
            target_paths.append(tp)
            paths += [(tp, j) for j in range(4)]
        else:
            p, v, *acc = _point_motion(obj, t, dt, rng)
            paths.append(PointPath(obj.motion, dt, p, v, acc[0] if acc else None))
            names.append(obj.name)
            pos_list.append(p)
            vel_list.append(v)
            rad_list.append(obj.radius)
            nrm_list.append(np.full((n, 3), np.nan))
    return Truth(
        t=t,
        names=names,
        positions=np.stack(pos_list, axis=1),
        velocities=np.stack(vel_list, axis=1),
        radii=np.array(rad_list),
        normals=np.stack(nrm_list, axis=1),
        targets=targets,
        paths=paths,
        target_paths=target_paths,
    )


def distractor_positions(scenario: Scenario, t: np.ndarray | None = None) -> np.ndarray:
    """Distractor centres at times ``t`` (default every frame): len(t) × distractors × 3."""
    if t is None:
        t = np.arange(scenario.frames) * scenario.dt
    t = np.atleast_1d(np.asarray(t, dtype=float))
    if not scenario.distractors:
        return np.zeros((len(t), 0, 3))
    return np.stack([_analytic(d.motion, t)[0] if d.motion is not None else np.array(d.position) + np.outer(t, d.velocity)
                     for d in scenario.distractors], axis=1)
