"""Four-point planar target: angle α and distance z from the image (Soifer, Fursov & Kharitonov;
Soifer, Fursov & Kharitonov §2), and the raw-measurement estimator.

Points 1 and 3 lie on one plate axis, 2 and 4 on the rotation axis, all at radius R from the
centre. With the centre on the optical axis at distance z and the plate turned by α, the image
distances (focal length f) of points 1 and 3 from the 2–4 line are::

    y1 = f R cos α / (z + R sin α),     y3 = f R cos α / (z − R sin α)

Exact inversion, valid for any z (derived from the two equations above; ``f = 1`` in normalized
image coordinates)::

    tan α = f (1/y1 − 1/y3) / 2,         z = f R cos α (1/y1 + 1/y3) / 2

The paper's eqs. (3)–(4), ``α = arcsin(f (y3 − y1) / (R (y3 + y1)))`` and ``z = 2Rf/(y1 + y3)``,
follow from ``(y3 − y1)/(y3 + y1) = R sin α / z`` with z replaced by f: (3) is exact only at
``z = f``, and (4) only at ``α = 0`` (at ``z = f`` it returns ``(f² − R² sin² α)/(f cos α)``).
They are kept as ``formula="paper"`` to measure that bias.

General configurations (the paper's ellipse construction): the centre's image is the intersection
of the image lines 1–3 and 2–4 (incidence survives projection); a virtual rotation of the camera
about its centre brings that ray onto the optical axis (the centre-offset correction), the 2–4
line gives the in-image axis direction, and y1, y3 are the distances of points 1 and 3 from it
in the rotated image. α and the centre are then mapped back to the reference (left) camera.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field

from pipeline.core.camera import Camera, StereoRig
from pipeline.estimators.base import Estimator, EstimatorConfig, Step
from pipeline.estimators.gating import camera_gate
from pipeline.estimators.registration import register

Formula = Literal["exact", "paper"]


def alpha_z_from_y(y1: float, y3: float, R: float, f: float = 1.0, formula: Formula = "exact") -> tuple[float, float, str]:
    """(α, z, flag) from the distances y1, y3 (same units as f). ``flag`` is "" when valid, else
    why not (degenerate geometry, |arcsin argument| > 1 under noise)."""
    if not (math.isfinite(y1) and math.isfinite(y3)) or y1 <= 0 or y3 <= 0:
        return math.nan, math.nan, "degenerate: points 1 and 3 not on opposite sides of the 2–4 axis"
    if formula == "exact":
        a = math.atan(f * (1.0 / y1 - 1.0 / y3) / 2.0)
        return a, f * R * math.cos(a) * (1.0 / y1 + 1.0 / y3) / 2.0, ""
    s = f * (y3 - y1) / (R * (y3 + y1))
    flag = ""
    if abs(s) > 1:
        flag = "arcsin argument beyond ±1 (clipped)"
        s = math.copysign(1.0, s)
    return math.asin(s), 2.0 * R * f / (y1 + y3), flag


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross`` of two 3-vectors, written out: the same products and differences (the same
    float result) without its axis handling, which cost more than the rest of a frame's geometry."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _rotation_to_axis(ray: np.ndarray) -> np.ndarray:
    """Rotation taking direction ``ray`` onto +z (Rodrigues), identity when already there."""
    r = ray / np.linalg.norm(ray)
    v = _cross(r, np.array([0.0, 0.0, 1.0]))
    s, c = np.linalg.norm(v), r[2]
    if s < 1e-15:
        return np.eye(3)
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx * ((1 - c) / s**2)


@dataclass
class TargetMeasurement:
    """One camera's (or the fused) measurement in the reference camera's frame."""

    alpha: float
    distance: float  # z coordinate of the plate centre in the reference frame
    center: np.ndarray  # plate centre, reference frame
    axis_angle: float  # in-image angle of the 2–4 axis
    flag: str = ""

    @property
    def ok(self) -> bool:
        return math.isfinite(self.alpha) and math.isfinite(self.distance)




def _failed(why: str, axis_angle: float = math.nan) -> TargetMeasurement:
    """No measurement, and why."""
    return TargetMeasurement(math.nan, math.nan, np.full(3, math.nan), axis_angle, why)


def measure_camera(points: np.ndarray, cam: Camera, R: float, formula: Formula = "exact",
                   to_reference: np.ndarray | None = None) -> TargetMeasurement:
    """α and z from one camera's four labelled pixel points (4×2, undistorted).

    ``to_reference`` (4×4) maps this camera's frame to the reference frame (identity for the
    left camera).
    """
    if points.shape != (4, 2) or not np.all(np.isfinite(points)):
        return _failed("fewer than four points")
    h = np.column_stack([cam.normalize(points), np.ones(4)])
    c = _cross(_cross(h[0], h[2]), _cross(h[1], h[3]))  # centre = line13 ∩ line24
    if not np.all(np.isfinite(c)) or abs(c[2]) <= 1e-12 * np.linalg.norm(c) or not np.any(c):
        return _failed("degenerate: collinear points")
    Rv = _rotation_to_axis(c / c[2])  # virtual camera looking at the centre
    q = h @ Rv.T
    q = q[:, :2] / q[:, 2:3]
    # each opposite pair (p, m) = images of C ± R v lies on a line through the (virtual) centre;
    # its distances r_p, r_m from the centre invert exactly like y1, y3: tilt β of v out of the
    # image plane and the distance D (the same equations as the exact α, z above).
    vecs, dists = [], []
    for p_, m_ in ((0, 2), (1, 3)):
        e = q[p_] - q[m_]
        if np.linalg.norm(e) < 1e-12:
            return _failed("degenerate: coincident points")
        e /= np.linalg.norm(e)
        beta, dist, flag = alpha_z_from_y(float(q[p_] @ e), float(-(q[m_] @ e)), R, 1.0, "exact")
        if flag:
            return _failed(flag)
        vecs.append(np.array([math.cos(beta) * e[0], math.cos(beta) * e[1], math.sin(beta)]))
        dists.append(dist)
    phi_v = math.atan2(vecs[1][1], vecs[1][0])
    if formula == "paper":
        got = _paper_orientation(q, vecs[1], phi_v, R)
        if isinstance(got, TargetMeasurement):
            return got
        normal_v, axis_v, dist_v, flag = got
    else:
        normal_v = _cross(vecs[0], vecs[1])  # (0,−cos α, sin α) × (1,0,0) = (0, sin α, cos α): flip to face the camera
        normal_v, axis_v, dist_v, flag = -normal_v / np.linalg.norm(normal_v), vecs[1], float(np.mean(dists)), ""
    if normal_v[2] >= 0:
        return _failed("inconsistent labels: the plate would face away from the camera", phi_v)
    normal, axis, center = Rv.T @ normal_v, Rv.T @ axis_v, Rv.T @ np.array([0.0, 0.0, dist_v])
    if to_reference is not None:
        normal, axis = to_reference[:3, :3] @ normal, to_reference[:3, :3] @ axis
        center = to_reference[:3, :3] @ center + to_reference[:3, 3]
    alpha, axis_angle = alpha_from_normal(normal, axis)
    return TargetMeasurement(alpha, float(center[2]), center, axis_angle, flag)


def _paper_orientation(q: np.ndarray, b_v: np.ndarray, phi_v: float, R: float
                       ) -> tuple[np.ndarray, np.ndarray, float, str] | TargetMeasurement:
    """The plate's normal, axis and distance in the virtual camera from the paper's eqs. (3)–(4)
    on the distances of points 1 and 3 from the 2–4 line (or why there are none)."""
    e = b_v[:2] / np.linalg.norm(b_v[:2])
    up = np.array([e[1], -e[0]])
    alpha_p, dist_v, flag = alpha_z_from_y(float(q[0] @ up), float(-(q[2] @ up)), R, 1.0, "paper")
    if not math.isfinite(alpha_p):
        return _failed(flag, phi_v)
    c_, s_ = math.cos(phi_v), math.sin(phi_v)
    Rz = np.array([[c_, -s_, 0.0], [s_, c_, 0.0], [0.0, 0.0, 1.0]])
    normal_v = Rz @ np.array([0.0, -math.sin(alpha_p), -math.cos(alpha_p)])
    return normal_v, np.array([math.cos(phi_v), math.sin(phi_v), 0.0]), dist_v, flag


def alpha_from_normal(normal: np.ndarray, axis: np.ndarray) -> tuple[float, float]:
    """α and the in-image axis angle φ of a plate with unit ``normal`` turning about ``axis``,
    inverting ``n = Rz(φ) (0, −sin α, −cos α)`` of :func:`renderers.motion.target_points`."""
    phi = math.atan2(axis[1], axis[0])
    c, s = math.cos(phi), math.sin(phi)
    n_local = np.array([c * normal[0] + s * normal[1], -s * normal[0] + c * normal[1], normal[2]])
    return math.atan2(-n_local[1], -n_local[2]), phi


def camera_to_left(rig: StereoRig, index: int) -> np.ndarray:
    """4×4 transform from camera ``index``'s frame to the left (reference) frame."""
    T = np.eye(4)
    if index == 1:
        T[:3, :3] = rig.R.T
        T[:3, 3] = -rig.R.T @ rig.T
    return T


#: the cameras a ``cameras`` setting measures with
CAMERA_INDICES: dict[str, tuple[int, ...]] = {"left": (0,), "right": (1,), "both": (0, 1)}


def measure_views(rig: StereoRig, obs: np.ndarray, R: float, formula: Formula = "exact",
                  cameras: Literal["left", "right", "both"] = "both") -> list[TargetMeasurement]:
    """Each measuring camera's own measurement from one frame's observation (4 points ×
    [u1, v1, u2, v2]), failed ones included (their flags say why)."""
    return [measure_camera(obs[:, 2 * c : 2 * c + 2], rig.cameras[c], R, formula, camera_to_left(rig, c))
            for c in CAMERA_INDICES[cameras]]


def measure_stereo(rig: StereoRig, obs: np.ndarray, R: float, formula: Formula = "exact",
                   cameras: Literal["left", "right", "both"] = "both") -> TargetMeasurement:
    """Measurement from one frame's observation (4 points × [u1, v1, u2, v2]); ``both`` averages
    the cameras' valid measurements (:func:`measure_views`)."""
    ms = measure_views(rig, obs, R, formula, cameras)
    good = [m for m in ms if m.ok]
    if not good:
        return TargetMeasurement(math.nan, math.nan, np.full(3, math.nan), math.nan,
                                 "; ".join(sorted({m.flag for m in ms if m.flag})) or "no measurement")
    if len(good) == 1:
        return good[0]
    return TargetMeasurement(float(np.mean([m.alpha for m in good])), float(np.mean([m.distance for m in good])),
                             np.mean([m.center for m in good], axis=0), good[0].axis_angle,
                             "; ".join(m.flag for m in good if m.flag))


class TargetConfig(EstimatorConfig):
    """Settings of the four-point target methods."""

    radius: float = Field(0.2, gt=0)  # R, metres
    """the target's radius R (m): the distance of each point from the plate's centre"""
    formula: Formula = "exact"
    """'exact' inversion of the four points, or the paper's approximate eqs. (3)–(4) ('paper')"""
    cameras: Literal["left", "right", "both"] = "both"
    """which cameras measure the target: 'left', 'right', or 'both' (their measurements averaged)"""


@register
class TargetEstimator(Estimator):
    """Four-point angle α and distance z measured frame by frame (Soifer et al.), no filter."""

    rig: StereoRig  # a stereo pair only (any_cameras is False: the base refuses a Rig)
    name = "four_point"
    #: whether the method takes the target's known dynamics (the clip's target ``config``): the
    #: raw measurement does not; the filters built on the target's model do
    models_target_dynamics: ClassVar[bool] = False
    kind = "target"
    Config: ClassVar[type[EstimatorConfig]] = TargetConfig
    config: TargetConfig  # the validated settings, of this method's own type

    def measure(self, obs: np.ndarray) -> TargetMeasurement:
        c = self.config
        return measure_stereo(self.rig, np.asarray(obs, dtype=float), c.radius, c.formula, c.cameras)

    @staticmethod
    def target_step(alpha: float, distance: float, center: np.ndarray, predicted: bool, gated: float | None = None,
                    **kw) -> Step:
        """A four-point step: the plate centre as position, α and z (and, for filters, whether the
        gate rejected this frame's measurement) in ``extra``."""
        extra = {"alpha": alpha, "distance": distance} | ({"gated": gated} if gated is not None else {})
        return Step(np.asarray(center, dtype=float), np.full(3, np.nan), predicted, extra=extra, **kw)

    def gated_measurement(self, u: np.ndarray, predicted: np.ndarray, S: np.ndarray) -> bool:
        """Whether a measurement ``u = [α, z]`` lies outside the χ² gate (2 dof, ``gate``) around the
        filter's predicted ``[α, z]`` with innovation covariance ``S``: a target whose points were
        mis-detected or mislabelled in one frame must not throw the filter off."""
        threshold = camera_gate(self.config.gate)
        if not np.isfinite(threshold):
            return False
        r = np.asarray(u, dtype=float) - predicted
        return bool(r @ np.linalg.solve(S, r) > threshold)

    def views(self, obs: np.ndarray) -> list[TargetMeasurement]:
        """Each measuring camera's own measurement (those that give none left out)."""
        c = self.config
        return [m for m in measure_views(self.rig, obs, c.radius, c.formula, c.cameras) if m.ok]

    def kept_view(self, obs: np.ndarray, predicted: np.ndarray, S: np.ndarray) -> TargetMeasurement | None:
        """When the fused measurement fails the gate: the one camera whose own measurement passes it
        (``S``: the innovation covariance with one camera's noise), None unless exactly one does. A
        plate mis-detected in one camera must not discard the other camera's good view of it."""
        views = self.views(np.asarray(obs, dtype=float))
        if len(views) < 2:
            return None
        kept = [m for m in views if not self.gated_measurement(np.array([m.alpha, m.distance]), predicted, S)]
        return kept[0] if len(kept) == 1 else None

    def _step(self, obs: np.ndarray) -> Step:
        m = self.measure(obs)
        return self.target_step(m.alpha, m.distance, m.center, not m.ok)
