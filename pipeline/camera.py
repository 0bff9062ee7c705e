"""The one camera model: pinhole projection, its Jacobian, the stereo rig, OpenCV<->OpenGL poses
and the calibration files (SPEC §2, §3).

Conventions: world frame = the left camera's frame, OpenCV axes (x right, y down, z forward),
metres; pixel (0, 0) is the centre of the top-left pixel. ``P = K [R | t]`` and
``X_right = R X_left + T`` as ``cv2.stereoCalibrate`` returns them. Every other module projects
through :func:`project` / :class:`Camera` / :class:`StereoRig`; there is no second copy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from pipeline.errors import CalibrationError
from pipeline.io import atomic_path

#: Flip between OpenCV camera axes (y down, z forward) and OpenGL's (y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


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

    @property
    def P(self) -> np.ndarray:
        """3×4 projection matrix ``K [R | t]``."""
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
            und = cv2.undistortPoints(pts, self.K, self.D, P=self.K)
            out[ok] = und.reshape(-1, 2)
        return out

    def gl_pose(self) -> np.ndarray:
        """Camera pose for pyrender (camera→world, OpenGL axes); see :func:`cv_to_gl_pose`."""
        return cv_to_gl_pose(self.R, self.t)

    def gl_intrinsics(self) -> tuple[float, float, float, float]:
        """``(fx, fy, cx, cy)`` to hand to ``pyrender.IntrinsicsCamera``.

        OpenGL puts pixel centres at +0.5, OpenCV at integers, so OpenCV's ``cx, cy`` are shifted by
        half a pixel (SPEC §2, the half-pixel trap); without it every render is (0.5, 0.5) px off.
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

    @property
    def baseline(self) -> float:
        return float(np.linalg.norm(self.right.center - self.left.center))

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
        fx, fy = (focal, focal) if np.isscalar(focal) else focal  # type: ignore[misc]
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

    def in_image(self, uv: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Whether pixel coordinates lie inside the image, ``margin`` px from its border."""
        w, h = self.image_size
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5 + margin) & (u <= w - 0.5 - margin) & (v >= -0.5 + margin) & (v <= h - 0.5 - margin)

    def check(self, source: str | Path | None = None) -> None:
        """Reject rigs no estimator can use (coincident cameras, singular intrinsics)."""
        for name, cam in (("left", self.left), ("right", self.right)):
            if not np.all(np.isfinite(cam.K)) or abs(np.linalg.det(cam.K)) < 1e-12:
                raise CalibrationError(f"{name} camera matrix is singular or not finite", source)
            if not np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-6):
                raise CalibrationError(f"{name} rotation is not orthonormal", source)
        if self.baseline < 1e-9:
            raise CalibrationError("the two cameras coincide (zero baseline): depth is unobservable", source)


# ---------------------------------------------------------------------------------------------
# Calibration files
# ---------------------------------------------------------------------------------------------

_DIST_LENGTHS = (4, 5, 8, 12, 14)


def _open_storage(path: Path) -> cv2.FileStorage:
    if not path.is_file():
        raise CalibrationError("calibration file not found", path)
    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:
        raise CalibrationError(f"not a readable OpenCV FileStorage file ({_first_line(exc)})", path) from None
    if not fs.isOpened():
        raise CalibrationError("not a readable OpenCV FileStorage file", path)
    return fs


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[-1].strip() if text else type(exc).__name__


def _read_mat(fs: cv2.FileStorage, key: str, path: Path, shape: tuple[int, ...] | None) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        raise CalibrationError(f"missing key '{key}'", path)
    mat = node.mat()
    if mat is None:
        raise CalibrationError(f"key '{key}' is not a matrix", path)
    mat = np.asarray(mat, dtype=float)
    if shape is not None and mat.size != int(np.prod(shape)):
        raise CalibrationError(f"key '{key}' has shape {mat.shape}, expected {shape}", path)
    if not np.all(np.isfinite(mat)):
        raise CalibrationError(f"key '{key}' contains NaN or infinite values", path)
    return mat.reshape(shape) if shape is not None else mat


def _read_intrinsics(fs: cv2.FileStorage, i: int, path: Path) -> np.ndarray:
    """``K1``/``K2`` (or the ``M1``/``M2`` of OpenCV's samples)."""
    for key in (f"K{i}", f"M{i}"):
        if not fs.getNode(key).empty():
            return _read_mat(fs, key, path, (3, 3))
    raise CalibrationError(f"missing key 'K{i}' (or 'M{i}')", path)


def _read_dist(fs: cv2.FileStorage, key: str, path: Path) -> np.ndarray:
    node = fs.getNode(key)
    if node.empty():
        return np.zeros(5)
    d = _read_mat(fs, key, path, None).ravel()
    if d.size not in _DIST_LENGTHS:
        raise CalibrationError(f"key '{key}' has {d.size} distortion coefficients; expected 4, 5, 8, 12 or 14", path)
    return d


def _read_size(fs: cv2.FileStorage, path: Path) -> tuple[int, int]:
    w, h = fs.getNode("image_width"), fs.getNode("image_height")
    if not w.empty() and not h.empty():
        return int(w.real()), int(h.real())
    size = fs.getNode("image_size")
    if not size.empty():
        m = size.mat()
        vals = np.asarray(m).ravel() if m is not None else [size.at(i).real() for i in range(size.size())]
        return int(vals[0]), int(vals[1])
    return (0, 0)


def load_calibration(path: str | Path) -> StereoRig:
    """Load a stereo calibration.

    ``path`` is a ``calib.yaml`` (keys ``K1 D1 K2 D2 R T`` and ``image_width``/``image_height``, as
    written by ``cv2.stereoCalibrate`` + ``cv2.FileStorage``), or a folder holding one, or a folder
    in the layout of OpenCV's ``stereo_calib`` sample (``intrinsics.yml`` with ``M1 D1 M2 D2``,
    ``extrinsics.yml`` with ``R T ...``). Both OpenCV 4 (``%YAML:1.0``) and 5 (``%YAML 1.2``) files
    load. Distortion may have 4, 5, 8, 12 or 14 coefficients.
    """
    path = Path(path)
    if path.is_dir():
        for name in ("calib.yaml", "calib.yml", "calib.xml", "calib.json"):
            if (path / name).is_file():
                return load_calibration(path / name)
        intr = next((path / n for n in ("intrinsics.yml", "intrinsics.yaml", "intrinsics.xml") if (path / n).is_file()), None)
        extr = next((path / n for n in ("extrinsics.yml", "extrinsics.yaml", "extrinsics.xml") if (path / n).is_file()), None)
        if intr is None or extr is None:
            raise CalibrationError("no calib.yaml (nor intrinsics.yml + extrinsics.yml) in this folder", path)
        return _load_stereo_calib_layout(intr, extr)
    return _load_stereo_calib_layout(path, path)


def _load_stereo_calib_layout(intr: Path, extr: Path) -> StereoRig:
    """Intrinsics (``K1/M1 D1 K2/M2 D2``, image size) from ``intr``, ``R T`` from ``extr`` (the same
    file for ``calib.yaml``)."""
    fs = _open_storage(intr)
    try:
        K1, K2 = (_read_intrinsics(fs, i, intr) for i in (1, 2))
        D1, D2 = _read_dist(fs, "D1", intr), _read_dist(fs, "D2", intr)
        size = _read_size(fs, intr)
    finally:
        fs.release()
    fs = _open_storage(extr)
    try:
        R, T = _read_mat(fs, "R", extr, (3, 3)), _read_mat(fs, "T", extr, (3,))
        if size == (0, 0):
            size = _read_size(fs, extr)
    finally:
        fs.release()
    rig = StereoRig(Camera(K1, D=D1), Camera(K2, R, T, D2), size)
    rig.check(extr)
    return rig


def save_calibration(rig: StereoRig, path: str | Path) -> None:
    """Write ``calib.yaml`` through ``cv2.FileStorage`` (atomically), with derived ``P1``, ``P2``."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fs = cv2.FileStorage(str(tmp), cv2.FILE_STORAGE_WRITE)
        fs.write("image_width", int(rig.image_size[0]))
        fs.write("image_height", int(rig.image_size[1]))
        fs.write("K1", rig.left.K)
        fs.write("D1", np.asarray(rig.left.D, dtype=float).reshape(1, -1))
        fs.write("K2", rig.right.K)
        fs.write("D2", np.asarray(rig.right.D, dtype=float).reshape(1, -1))
        fs.write("R", rig.R)
        fs.write("T", rig.T.reshape(3, 1))
        fs.write("P1", rig.left.P)
        fs.write("P2", rig.right.P)
        fs.release()
