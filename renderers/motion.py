"""Ground-truth motion: per-frame 3-D positions and velocities of every marker of a scenario.

Pure numpy and seeded (``numpy.random.default_rng([seed, object_index])``), so the same scenario
and seed give identical truth, bit for bit, whether or not anything is rendered.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

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
    """Four-point target state per frame (SPEC §3 ``target_truth.csv``)."""

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


@dataclass
class Truth:
    """Per-frame truth of all markers: ``positions``/``velocities`` are frames × markers × 3."""

    t: np.ndarray
    names: list[str]
    positions: np.ndarray
    velocities: np.ndarray
    radii: np.ndarray
    #: per marker: unit normal of a flat (disc) marker per frame, or NaN for spheres (frames×markers×3)
    normals: np.ndarray
    targets: list[TargetTruth]

    @property
    def n_frames(self) -> int:
        return len(self.t)


def target_rotation(axis_angle: float) -> np.ndarray:
    """In-image rotation of the target frame about the optical axis by ``axis_angle`` (rad)."""
    c, s = math.cos(axis_angle), math.sin(axis_angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def target_points(center: np.ndarray, alpha: np.ndarray, radius: float, axis_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The four target points (frames × 4 × 3) and the plate normal (frames × 3).

    Numbering (SPEC §4.8): 2 and 4 lie on the rotation axis ``b`` (image x for ``axis_angle = 0``),
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
    from scipy.linalg import expm  # imported here: render workers start faster without scipy

    F = expm(A * dt)
    out = np.empty((n, 2))
    x = np.asarray(x0, dtype=float)
    for k in range(n):
        out[k] = x
        x = F @ x
        if noise > 0:
            x = x + np.array([0.0, noise * math.sqrt(dt) * rng.standard_normal()])
    return out


def _point_motion(obj: ObjectSpec, t: np.ndarray, dt: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    m = obj.motion
    n = len(t)
    if isinstance(m, ConstantVelocity):
        p0, v0 = np.array(m.start, float), np.array(m.velocity, float)
        if m.process_noise == 0:
            return p0 + np.outer(t, v0), np.tile(v0, (n, 1))
        pos, vel = np.empty((n, 3)), np.empty((n, 3))
        p, v = p0, v0
        acc = rng.standard_normal((n, 3)) * m.process_noise
        for k in range(n):
            pos[k], vel[k] = p, v
            p = p + v * dt + 0.5 * acc[k] * dt * dt
            v = v + acc[k] * dt
        return pos, vel
    if isinstance(m, ConstantAcceleration):
        p0, v0, a0 = (np.array(x, float) for x in (m.start, m.velocity, m.acceleration))
        return p0 + np.outer(t, v0) + 0.5 * np.outer(t * t, a0), v0 + np.outer(t, a0)
    if isinstance(m, Sinusoid):
        c, amp, ph = (np.array(x, float) for x in (m.center, m.amplitude, m.phase))
        w = 2 * math.pi * np.broadcast_to(np.array(m.frequency_hz, float), (3,))
        arg = np.outer(t, w) + ph
        return c + amp * np.sin(arg), amp * w * np.cos(arg)
    raise TypeError(f"not a point motion: {type(m).__name__}")


def simulate_truth(scenario: Scenario) -> Truth:
    """Positions and velocities of every marker at every frame of ``scenario``."""
    n, dt = scenario.frames, scenario.dt
    t = np.arange(n) * dt
    names: list[str] = []
    pos_list, vel_list, rad_list, nrm_list = [], [], [], []
    targets: list[TargetTruth] = []
    for idx, obj in enumerate(scenario.objects):
        rng = np.random.default_rng([scenario.seed, idx])
        m = obj.motion
        if isinstance(m, FourPointTarget):
            al = _second_order(np.array(m.alpha_matrix, float), [m.alpha0, m.alpha_rate0], m.alpha_noise, n, dt, rng)
            Az = np.array([[0.0, 1.0], [0.0, m.a_z]])
            zz = _second_order(Az, [m.distance0, m.distance_rate0], m.distance_noise, n, dt, rng)
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
        else:
            p, v = _point_motion(obj, t, dt, rng)
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
    )


def distractor_positions(scenario: Scenario) -> np.ndarray:
    """Distractor centres per frame (frames × distractors × 3)."""
    t = np.arange(scenario.frames) * scenario.dt
    if not scenario.distractors:
        return np.zeros((scenario.frames, 0, 3))
    return np.stack([np.array(d.position) + np.outer(t, d.velocity) for d in scenario.distractors], axis=1)
