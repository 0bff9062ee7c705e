"""The one camera model: pinhole projection, its Jacobian, the stereo rig, the measurement model
and OpenCV<->OpenGL poses (calibration files: :mod:`pipeline.core.calibration`).

Conventions: world frame = the left camera's frame, OpenCV axes (x right, y down, z forward),
metres; pixel (0, 0) is the centre of the top-left pixel. ``P = K [R | t]`` and
``X_right = R X_left + T`` as ``cv2.stereoCalibrate`` returns them. Every other module projects
through :func:`project` / :class:`Camera` / :class:`StereoRig`; there is no second copy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Protocol

import numpy as np

from pipeline.core.errors import CalibrationError
from pipeline.core.lazy import lazy_module
from pipeline.core.memo import RowMemo

if TYPE_CHECKING:
    import cv2
else:
    cv2 = lazy_module("cv2")  # imported on first use: --help and `methods` need no OpenCV

#: single observations a rig remembers the triangulation of (a long clip's frames × a marker or two)
MEMO_SIZE = 20_000
#: ``cv2.undistortPoints``' COUNT | EPS criteria: OpenCV's 5 iterations leave corners off by tenths of a pixel
UNDISTORT_CRITERIA = (1 | 2, 100, 1e-12)

#: Flip between OpenCV camera axes (y down, z forward) and OpenGL's (y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


class Views(Protocol):
    """What the measurement model asks of a set of cameras: a :class:`StereoRig`, or the N-camera
    :class:`~pipeline.core.rig.Rig`."""

    @property
    def cameras(self) -> tuple[Camera, ...]: ...
    @property
    def names(self) -> tuple[str, ...]: ...
    @property
    def n(self) -> int: ...
    @property
    def baseline(self) -> float: ...
    @property
    def sizes(self) -> tuple[tuple[int, int], ...]: ...
    def project(self, X: np.ndarray) -> np.ndarray: ...
    def jacobian(self, X: np.ndarray) -> np.ndarray: ...
    def depths(self, X: np.ndarray) -> np.ndarray: ...
    def triangulate(self, Y: np.ndarray) -> np.ndarray: ...


def project(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Project points ``X`` (N×3 or 3) with a 3×4 matrix ``P``: ``x ~ P [X; 1]`` → N×2 pixels."""
    X = np.asarray(X, dtype=float)
    Xh = X[..., :3] @ P[:, :3].T + P[:, 3]
    return Xh[..., :2] / Xh[..., 2:3]


def project_jacobian(P: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Analytic Jacobian d(u, v)/dX of :func:`project` at points ``X`` (N×3 → N×2×3).

    With ``q = P[:, :3] X + P[:, 3]``: ``du/dX = (p1 − u p3) / q3``, ``dv/dX = (p2 − v p3) / q3``.
    """
    X = np.asarray(X, dtype=float)
    M = P[:, :3]
    q = X @ M.T + P[:, 3]
    uv = q[..., :2] / q[..., 2:3]
    J = M[:2] - uv[..., :, None] * M[2]
    return J / q[..., 2, None, None]


def rotation_y(angle: float) -> np.ndarray:
    """Rotation by ``angle`` radians about the y axis (right-handed)."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


@dataclass(frozen=True)
class Camera:
    """A calibrated camera: intrinsics ``K``, distortion ``D``, world→camera pose ``R``, ``t``."""

    K: np.ndarray
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    D: np.ndarray = field(default_factory=lambda: np.zeros(5))

    @cached_property
    def P(self) -> np.ndarray:
        """3×4 projection matrix ``K [R | t]`` (computed once: cameras are immutable)."""
        return self.K @ np.hstack([self.R, self.t.reshape(3, 1)])

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, ``−Rᵀ t``."""
        return -self.R.T @ self.t

    def project(self, X: np.ndarray) -> np.ndarray:
        """Pixel coordinates of world points (distortion-free pinhole)."""
        return project(self.P, X)

    def jacobian(self, X: np.ndarray) -> np.ndarray:
        """d(u, v)/dX at world points, N×2×3."""
        return project_jacobian(self.P, X)

    def project_distorted(self, X: np.ndarray) -> np.ndarray:
        """Pixel coordinates as the lens images world points: ``cv2.projectPoints`` with ``D``
        (the pinhole :meth:`project` when there is no distortion). N×3 → N×2."""
        X = np.asarray(X, dtype=float).reshape(-1, 3)
        if not np.any(self.D) or len(X) == 0:
            return self.project(X)
        rvec, _ = cv2.Rodrigues(self.R)
        uv, _ = cv2.projectPoints(X, rvec, self.t.astype(float), self.K, self.D)
        return uv.reshape(-1, 2)

    def depth(self, X: np.ndarray) -> np.ndarray:
        """z coordinate of world points in this camera's frame (positive in front)."""
        return np.asarray(X, dtype=float)[..., :3] @ self.R[2] + self.t[2]

    def normalize(self, uv: np.ndarray) -> np.ndarray:
        """Pixels → normalized image coordinates ``((u − cx)/fx, (v − cy)/fy)`` (no distortion)."""
        uv = np.asarray(uv, dtype=float)
        K = self.K
        x = (uv[..., 0] - K[0, 2] - K[0, 1] * (uv[..., 1] - K[1, 2]) / K[1, 1]) / K[0, 0]
        y = (uv[..., 1] - K[1, 2]) / K[1, 1]
        return np.stack([x, y], axis=-1)

    def undistort(self, uv: np.ndarray) -> np.ndarray:
        """Remove lens distortion from pixel coordinates (``cv2.undistortPoints`` with ``P = K``)."""
        uv = np.asarray(uv, dtype=float)
        if not np.any(self.D) or uv.size == 0:
            return uv.copy()
        out = np.full_like(uv, np.nan)
        ok = np.all(np.isfinite(uv), axis=-1)
        if ok.any():
            pts = uv[ok].reshape(-1, 1, 2)
            und = cv2.undistortPoints(pts, self.K, self.D, P=self.K, criteria=UNDISTORT_CRITERIA)
            out[ok] = und.reshape(-1, 2)
        return out

    def gl_pose(self) -> np.ndarray:
        """Camera pose for pyrender (camera→world, OpenGL axes); see :func:`cv_to_gl_pose`."""
        return cv_to_gl_pose(self.R, self.t)

    def gl_intrinsics(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` to hand to ``pyrender.IntrinsicsCamera``.

        OpenGL puts pixel centres at +0.5, OpenCV at integers, so OpenCV's ``cx, cy`` are shifted by
        half a pixel; without it every render is (0.5, 0.5) px off.
        """
        K = self.K
        return float(K[0, 0]), float(K[1, 1]), float(K[0, 2]) + 0.5, float(K[1, 2]) + 0.5


def cv_to_gl_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """OpenCV world→camera ``[R|t]`` → pyrender camera pose: ``inv([R|t]) @ diag(1, −1, −1, 1)``."""
    Rt = np.eye(4)
    Rt[:3, :3] = R
    Rt[:3, 3] = np.asarray(t, dtype=float).reshape(3)
    return np.linalg.inv(Rt) @ CV_TO_GL


@dataclass(frozen=True)
class StereoRig:
    """Two cameras; the left one defines the world frame. ``R, T``: ``X_right = R X_left + T``."""

    left: Camera
    right: Camera
    image_size: tuple[int, int]  # (width, height)

    @property
    def R(self) -> np.ndarray:
        return self.right.R

    @property
    def T(self) -> np.ndarray:
        return self.right.t

    @property
    def cameras(self) -> tuple[Camera, Camera]:
        return (self.left, self.right)

    #: the number of cameras, and their names (what a :class:`~pipeline.core.rig.Rig` of two would say)
    n = 2
    names = ("left", "right")

    @cached_property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.right.center - self.left.center))

    @cached_property
    def dlt_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """Both cameras' ``K [R | t/b]`` (baseline units), the DLT's unit-free projections."""
        b = self.baseline
        left, right = (c.K @ np.hstack([c.R, c.t.reshape(3, 1) / b]) for c in self.cameras)
        return left, right

    @classmethod
    def from_parameters(
        cls,
        width: int,
        height: int,
        focal: float | tuple[float, float],
        principal_point: tuple[float, float] | None = None,
        baseline: float = 0.3,
        toe_in_deg: float = 0.0,
    ) -> StereoRig:
        """Build a rig from resolution, focal length(s) in pixels, principal point (pixels, default
        the image centre), baseline (m) and toe-in: the convergence angle between the optical axes.

        The right camera sits at ``(baseline, 0, 0)`` turned about its y axis towards the left
        camera's optical axis by ``toe_in``; both share the intrinsics.
        """
        fx, fy = (focal, focal) if isinstance(focal, (int, float)) else focal
        cx, cy = principal_point if principal_point is not None else ((width - 1) / 2, (height - 1) / 2)
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        R_wc = rotation_y(-math.radians(toe_in_deg))  # right camera → world
        C = np.array([baseline, 0.0, 0.0])
        R = R_wc.T
        return cls(Camera(K.copy()), Camera(K.copy(), R, -R @ C), (int(width), int(height)))

    def project(self, X: np.ndarray) -> np.ndarray:
        """Stereo observation ``h(X) = [u1, v1, u2, v2]`` of world points (N×4)."""
        return np.concatenate([self.left.project(X), self.right.project(X)], axis=-1)

    def jacobian(self, X: np.ndarray) -> np.ndarray:
        """d h / dX, N×4×3."""
        return np.concatenate([self.left.jacobian(X), self.right.jacobian(X)], axis=-2)

    def normalized(self) -> StereoRig:
        """The same rig with ``K = I``: projections come out in normalized image coordinates."""
        eye = np.eye(3)
        return StereoRig(
            Camera(eye, self.left.R, self.left.t), Camera(eye, self.right.R, self.right.t), self.image_size
        )

    def normalize(self, obs: np.ndarray) -> np.ndarray:
        """Pixel observations ``[u1, v1, u2, v2]`` (…×4) → normalized image coordinates."""
        obs = np.asarray(obs, dtype=float)
        return np.concatenate([self.left.normalize(obs[..., :2]), self.right.normalize(obs[..., 2:4])], -1)

    @property
    def sizes(self) -> tuple[tuple[int, int], tuple[int, int]]:
        """Each camera's image size (one for both: a :class:`Rig`'s interface)."""
        return (self.image_size, self.image_size)

    def in_image(self, uv: np.ndarray, margin: float = 0.0, camera: int = 0) -> np.ndarray:
        """Whether pixel coordinates lie inside the image, ``margin`` px from its border."""
        w, h = self.image_size
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5 + margin) & (u <= w - 0.5 - margin) & (v >= -0.5 + margin) & (v <= h - 0.5 - margin)

    def scaled_to(self, size: tuple[int, int]) -> StereoRig:
        """The same rig for images resized to ``size`` (width, height): K's rows scale with the
        image (pixel centres stay at integers, so ``c' = (c + 0.5)·s − 0.5``)."""
        sx, sy = size[0] / self.image_size[0], size[1] / self.image_size[1]
        S = np.array([[sx, 0.0, 0.5 * sx - 0.5], [0.0, sy, 0.5 * sy - 0.5], [0.0, 0.0, 1.0]])
        return StereoRig(Camera(S @ self.left.K, self.left.R, self.left.t, self.left.D),
                         Camera(S @ self.right.K, self.right.R, self.right.t, self.right.D), (int(size[0]), int(size[1])))

    def fundamental(self) -> np.ndarray:
        """Fundamental matrix ``F`` with ``x_rightᵀ F x_left = 0``: ``K2⁻ᵀ [T]ₓ R K1⁻¹`` (H&Z 9.2)."""
        return fundamental(self.left, self.right)

    def epipolar_distance(self, obs: np.ndarray) -> np.ndarray:
        """Symmetric point-to-epipolar-line distance (px) of stereo observations ``[u1, v1, u2, v2]``
        (N×4): the mean of the right point's distance to ``F x1`` and the left's to ``Fᵀ x2``."""
        obs = np.asarray(obs, dtype=float).reshape(-1, 4)
        F = self.fundamental()
        x1 = np.column_stack([obs[:, :2], np.ones(len(obs))])
        x2 = np.column_stack([obs[:, 2:], np.ones(len(obs))])
        l2, l1 = x1 @ F.T, x2 @ F
        alg = np.abs(np.sum(x2 * l2, axis=1))
        with np.errstate(divide="ignore", invalid="ignore"):
            return 0.5 * (alg / np.hypot(l2[:, 0], l2[:, 1]) + alg / np.hypot(l1[:, 0], l1[:, 1]))

    def triangulate(self, Y: np.ndarray) -> np.ndarray:
        """The inverse of :meth:`project`: DLT triangulation of stereo observations (…×4 pixels →
        …×3; NaN where a camera is missing). See :func:`triangulate`. A single observation (an
        estimator's step) is remembered: every method of a run triangulates the same detections."""
        Y = np.asarray(Y, dtype=float)
        if Y.size == 4:
            return self._points.get(Y.reshape(1, 4), lambda y: triangulate(self, y)[0]).reshape(*Y.shape[:-1], 3)
        return triangulate(self, Y.reshape(-1, 4)).reshape(*Y.shape[:-1], 3)

    def remember(self, Y: np.ndarray) -> None:
        """Triangulate observations (N×4) at once for :meth:`triangulate` to find one by one, the
        same bits (LAPACK solves each row alone either way); workers forked after this inherit them."""
        Y = np.unique(np.asarray(Y, dtype=float).reshape(-1, 4)[:MEMO_SIZE], axis=0)
        self._points.fill(Y, triangulate(self, Y))

    @cached_property
    def _points(self) -> RowMemo:
        return RowMemo(MEMO_SIZE)

    def depths(self, X: np.ndarray) -> np.ndarray:
        """Depth of world points in the left and the right camera (N×2); ≤ 0 means behind it."""
        return np.stack([self.left.depth(X), self.right.depth(X)], axis=-1)

    def check(self, source: str | Path | None = None) -> None:
        """Reject rigs no estimator can use (coincident cameras, singular intrinsics)."""
        for name, cam in (("left", self.left), ("right", self.right)):
            if not np.all(np.isfinite(cam.K)) or abs(np.linalg.det(cam.K)) < 1e-12:
                raise CalibrationError(f"{name} camera matrix is singular or not finite", source)
            if not np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-6):
                raise CalibrationError(f"{name} rotation is not orthonormal", source)
        if self.baseline < 1e-9:
            raise CalibrationError("the two cameras coincide (zero baseline): depth is unobservable", source)


def triangulate(rig: StereoRig, Y: np.ndarray) -> np.ndarray:
    """Stereo triangulation by the homogeneous DLT (thesis ch. I; Hartley & Zisserman §12.2), the
    inverse of :meth:`StereoRig.project`: N×4 pixels → N×3 points, NaN where a camera is missing.

    For observations ``(u1, v1)``, ``(u2, v2)`` and cameras ``P1``, ``P2`` with rows ``pᵢʲᵀ``::

        A = [u1 p1³ᵀ − p1¹ᵀ;  v1 p1³ᵀ − p1²ᵀ;  u2 p2³ᵀ − p2¹ᵀ;  v2 p2³ᵀ − p2²ᵀ]

    and the point is the right singular vector of ``A`` for its smallest singular value; rows are
    scaled to unit norm (conditioning). Unit covariance: that row scaling would weight the equations
    differently for ``T`` in millimetres and in metres, so the DLT is solved for ``X / b`` (``b``
    the baseline; ``T/b`` is unit-free) and scaled back: scaling ``T`` by ``s`` scales every point
    by exactly ``s``.
    """
    Y = np.asarray(Y, dtype=float).reshape(-1, 4)
    b = rig.baseline
    P1, P2 = rig.dlt_matrices
    A = np.empty((len(Y), 4, 4))
    A[:, 0] = Y[:, 0, None] * P1[2] - P1[0]
    A[:, 1] = Y[:, 1, None] * P1[2] - P1[1]
    A[:, 2] = Y[:, 2, None] * P2[2] - P2[0]
    A[:, 3] = Y[:, 3, None] * P2[2] - P2[1]
    ok = np.all(np.isfinite(Y), axis=1)
    out = np.full((len(Y), 3), np.nan)
    if not ok.any():
        return out
    A = A[ok] / np.linalg.norm(A[ok], axis=2, keepdims=True)
    _, _, Vt = np.linalg.svd(A)
    Xh = Vt[:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4]
    X[~np.isfinite(X).all(axis=1)] = np.nan
    out[ok] = X * b
    return out


def fundamental(a: Camera, b: Camera) -> np.ndarray:
    """``F`` with ``x_bᵀ F x_a = 0`` between two cameras (Hartley & Zisserman, eq. 9.2)."""
    R = b.R @ a.R.T
    t = np.ravel(b.t) - R @ np.ravel(a.t)
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(b.K).T @ tx @ R @ np.linalg.inv(a.K)


def epipolar_distances(a: Camera, b: Camera, ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Symmetric point-to-epipolar-line distances (px) of every pair of ``ua`` (m × 2) and ``ub`` (n × 2)."""
    F = fundamental(a, b)
    xa, xb = np.c_[ua, np.ones(len(ua))], np.c_[ub, np.ones(len(ub))]
    lb, la = xa @ F.T, xb @ F  # lines in b of a's points, in a of b's points
    alg = np.abs(xb @ F @ xa.T).T  # m × n
    return 0.5 * (alg / np.hypot(lb[:, 0], lb[:, 1])[:, None] + alg / np.hypot(la[:, 0], la[:, 1])[None, :])


def triangulate_views(cameras: list[Camera], uv: np.ndarray) -> np.ndarray:
    """The homogeneous DLT over the cameras whose pixel (``uv``: 2·cameras, NaN missing) is given."""
    rows = []
    for c, cam in enumerate(cameras):
        u, v = uv[2 * c : 2 * c + 2]
        if np.isfinite(u) and np.isfinite(v):
            rows += [u * cam.P[2] - cam.P[0], v * cam.P[2] - cam.P[1]]
    if len(rows) < 4:
        return np.full(3, np.nan)
    X = np.linalg.svd(np.array(rows))[2][-1]
    return X[:3] / X[3]


def linearize_point(Pm, delta, x, h, H):
    """``h(x)`` (4) and ``∂h/∂x`` (4 × 6) of one state through both cameras' 3 × 4 matrices ``Pm``
    (2 × 3 × 4), the right camera seeing ``p + v·δ``, into ``h`` and ``H``: the measurement model of
    :meth:`StereoMeasurementModel.linearize` written for one state in scalar arithmetic, so that the
    compiled filters compile this very function (:mod:`pipeline.estimators.compiled`) instead of a
    copy of it (tested equal to the vectorised form)."""
    for c in range(2):
        dc = delta if c == 1 else 0.0
        p0, p1, p2 = x[0] + x[3] * dc, x[1] + x[4] * dc, x[2] + x[5] * dc
        q2 = Pm[c, 2, 0] * p0 + Pm[c, 2, 1] * p1 + Pm[c, 2, 2] * p2 + Pm[c, 2, 3]
        for r in range(2):
            uv = (Pm[c, r, 0] * p0 + Pm[c, r, 1] * p1 + Pm[c, r, 2] * p2 + Pm[c, r, 3]) / q2
            h[2 * c + r] = uv
            for a in range(3):
                J = (Pm[c, r, a] - uv * Pm[c, 2, a]) / q2
                H[2 * c + r, a] = J
                H[2 * c + r, 3 + a] = dc * J


@dataclass(frozen=True)
class StereoMeasurementModel:
    """The measurement model every estimator uses (Stone Soup's ``function / jacobian /
    inverse_function``): for a state whose first three components are the position ``p``,

        y = h(x) + v,   h(x) = [proj(P1, p); proj(P2, p); …] (pixels),   v ~ N(0, σ² I₂ₙ)

    for the N cameras of ``rig`` (a :class:`StereoRig`, or a :class:`Rig` of N ≥ 2).

    ``jacobian`` is ``[∂h/∂p, 0]`` (zeros for the other state components) and ``inverse_function``
    is the DLT triangulation; ``inverse_covariance`` propagates the pixel noise to the triangulated
    point to first order, ``σ² (JᵀJ)⁻¹``.
    """

    rig: StereoRig | Views
    pixel_sigma: float = 1.0
    ndim_state: int = 6
    #: δ (s): the right camera's frame k is exposed δ after the left camera's. A state at the left
    #: camera's time is seen by the right camera at ``p + v·δ`` (velocity in components 3–5).
    #: Two cameras only.
    time_offset: float = 0.0

    def __post_init__(self) -> None:
        if self.time_offset and self.rig.n != 2:
            raise CalibrationError(f"a time offset is modelled for two cameras, not {self.rig.n}")

    @property
    def ndim_meas(self) -> int:
        """2N: a pixel (u, v) per camera."""
        return 2 * self.rig.n

    def function(self, x: np.ndarray) -> np.ndarray:
        """``h(x) = [proj(P1, p); proj(P2, p + v·δ); …]``: …×ndim_state (or …×3, δ ignored) → …×2N pixels."""
        x = np.asarray(x, dtype=float)
        p = x[..., :3]
        if self.time_offset == 0.0 or x.shape[-1] < 6:
            return self.rig.project(p)
        a, b = self.rig.cameras[:2]
        return np.concatenate([a.project(p), b.project(p + x[..., 3:6] * self.time_offset)], -1)

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """``∂h/∂x``: …×ndim_state → …×2N×ndim_state; with a time offset the right camera's rows gain
        ``δ·∂proj₂/∂p`` on the velocity."""
        x = np.asarray(x, dtype=float)
        pad = np.zeros((*x.shape[:-1], self.ndim_meas, self.ndim_state - 3))
        if self.time_offset == 0.0:
            return np.concatenate([self.rig.jacobian(x[..., :3]), pad], axis=-1)
        p = x[..., :3]
        a, b = self.rig.cameras[:2]
        Jr = b.jacobian(p + x[..., 3:6] * self.time_offset)
        J = np.concatenate([a.jacobian(p), Jr], axis=-2)
        pad[..., 2:, :3] = self.time_offset * Jr
        return np.concatenate([J, pad], axis=-1)

    @cached_property
    def _stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """Every camera's ``P[:, :3]`` (N×3×3) and ``P[:, 3]`` (N×3), for :meth:`linearize`."""
        P = np.stack([c.P for c in self.rig.cameras])
        return P[:, :, :3].copy(), P[:, :, 3].copy()

    def linearize(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(h(x), ∂h/∂x)`` of one state vector in one pass: what an EKF update needs, the same
        numbers as :meth:`function` and :meth:`jacobian` (tested) at a third of their cost."""
        M, c = self._stacked
        p = np.stack([x[:3], x[:3] + x[3:6] * self.time_offset]) if self.time_offset else x[:3]
        q = (M @ p[..., None])[..., 0] + c if p.ndim == 2 else M @ p + c  # N×3: one row per camera
        uv = q[:, :2] / q[:, 2:3]
        J = (M[:, :2] - uv[:, :, None] * M[:, 2:3]) / q[:, 2, None, None]  # N×2×3
        m = self.ndim_meas
        H = np.zeros((m, self.ndim_state))
        H[:, :3] = J.reshape(m, 3)
        if self.time_offset:
            H[2:, 3:6] = self.time_offset * J[1]
        return uv.reshape(m), H

    def inverse_function(self, y: np.ndarray) -> np.ndarray:
        """``h⁻¹(y)``: …×2N pixels → …×3 positions (the DLT over the cameras present; NaN with
        fewer than two)."""
        return self.rig.triangulate(y)

    def covar(self) -> np.ndarray:
        """Measurement noise covariance ``R = σ² I₂ₙ``."""
        return np.eye(self.ndim_meas) * self.pixel_sigma**2

    def inverse_covariance(self, X: np.ndarray) -> np.ndarray:
        """Covariance of the triangulated point ``X`` (…×3 → …×3×3), ``σ² (JᵀJ)⁻¹``."""
        J = self.rig.jacobian(np.asarray(X, dtype=float))
        return self.pixel_sigma**2 * np.linalg.inv(np.swapaxes(J, -1, -2) @ J)
