"""A rig of N ≥ 2 named cameras (the motion-capture layout and every file format's), the stereo
pair being its two-camera case, and triangulation over any subset of its cameras — robust to a
camera whose ray disagrees. The camera model itself is :mod:`pipeline.core.camera`'s."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from pipeline.core.camera import Camera, StereoRig
from pipeline.core.errors import CalibrationError


@dataclass(frozen=True)
class Rig:
    """N ≥ 2 named cameras, each with its image size and time offset (seconds its frame k is
    exposed after camera 0's). Poses are world → camera; the world is whatever frame the rig's file
    uses (:meth:`in_frame_of` re-expresses it in one camera's). A :class:`StereoRig` is the N = 2
    case: :meth:`from_stereo` and :meth:`stereo` go between them."""

    cameras: tuple[Camera, ...]
    names: tuple[str, ...]
    sizes: tuple[tuple[int, int], ...]  # (width, height) per camera
    offsets: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.cameras)
        if not self.offsets:
            object.__setattr__(self, "offsets", (0.0,) * n)
        if not (len(self.names) == len(self.sizes) == len(self.offsets) == n):
            raise CalibrationError(f"a rig needs a name, a size and an offset per camera ({n} cameras)")

    @property
    def n(self) -> int:
        return len(self.cameras)

    @property
    def image_size(self) -> tuple[int, int]:
        """The first camera's image size (width, height); :attr:`sizes` has every camera's."""
        return self.sizes[0]

    def in_image(self, uv: np.ndarray, margin: float = 0.0, camera: int = 0) -> np.ndarray:
        """Whether pixel coordinates lie inside camera ``camera``'s image, ``margin`` px from its border."""
        w, h = self.sizes[camera]
        u, v = uv[..., 0], uv[..., 1]
        return (u >= -0.5 + margin) & (u <= w - 0.5 - margin) & (v >= -0.5 + margin) & (v <= h - 0.5 - margin)

    @cached_property
    def baseline(self) -> float:
        """The longest distance between two camera centres (the rig's length scale)."""
        C = np.array([c.center for c in self.cameras])
        return float(np.max(np.linalg.norm(C[:, None] - C[None], axis=-1)))

    def project(self, X: np.ndarray) -> np.ndarray:
        """``h(X) = [u₀, v₀, u₁, v₁, …]`` of world points (…×2N, pinhole)."""
        return np.concatenate([c.project(X) for c in self.cameras], axis=-1)

    def jacobian(self, X: np.ndarray) -> np.ndarray:
        """d h / dX, …×2N×3."""
        return np.concatenate([c.jacobian(X) for c in self.cameras], axis=-2)

    def depths(self, X: np.ndarray) -> np.ndarray:
        """Depth of world points in every camera (…×N); ≤ 0 means behind it."""
        return np.stack([c.depth(X) for c in self.cameras], axis=-1)

    def triangulate(self, Y: np.ndarray) -> np.ndarray:
        """Linear (DLT) triangulation over every camera that has an observation (…×2N → …×3;
        NaN with fewer than two): :func:`triangulate_subset` over all cameras."""
        Y = np.asarray(Y, dtype=float)
        flat = Y.reshape(-1, 2 * self.n)
        seen = np.isfinite(flat).reshape(-1, self.n, 2).all(axis=2)
        out = np.full((len(flat), 3), np.nan)
        for mask in {tuple(m) for m in seen[seen.sum(axis=1) >= 2].tolist()}:
            rows = np.all(seen == np.array(mask), axis=1)
            out[rows] = triangulate_subset(self, flat[rows], np.flatnonzero(mask))
        return out.reshape(*Y.shape[:-1], 3)

    @classmethod
    def from_stereo(cls, stereo: StereoRig, time_offset: float = 0.0) -> Rig:
        """A stereo pair as a two-camera rig named ``left``, ``right`` (the right camera ``time_offset`` s late)."""
        return cls(stereo.cameras, stereo.names, stereo.sizes, (0.0, float(time_offset)))

    def in_frame_of(self, i: int = 0) -> Rig:
        """The same rig with camera ``i``'s frame as the world (its pose becomes ``I, 0``)."""
        ref = self.cameras[i]
        cams = tuple(Camera(c.K, c.R @ ref.R.T, np.ravel(c.t) - c.R @ ref.R.T @ np.ravel(ref.t), c.D)
                     for c in self.cameras)
        return Rig(cams, self.names, self.sizes, self.offsets)

    def stereo(self, i: int = 0, j: int = 1) -> StereoRig:
        """Cameras ``i`` and ``j`` as a :class:`StereoRig` (world: camera ``i``'s frame)."""
        r = self.in_frame_of(i)
        if self.sizes[i] != self.sizes[j]:
            raise CalibrationError(f"cameras {self.names[i]} and {self.names[j]} differ in image size "
                                   f"({self.sizes[i]} and {self.sizes[j]}): a stereo pair needs one")
        return StereoRig(r.cameras[i], r.cameras[j], self.sizes[i])

    def check(self, source: str | Path | None = None) -> None:
        """Reject rigs no estimator can use (singular intrinsics, coincident cameras)."""
        if self.n < 2:
            raise CalibrationError(f"a rig needs at least two cameras, this one has {self.n}", source)
        if len(set(self.names)) != self.n:
            raise CalibrationError(f"camera names repeat: {', '.join(self.names)}", source)
        for name, cam, (w, h) in zip(self.names, self.cameras, self.sizes, strict=True):
            _check_camera(cam, name, source)
            if w < 0 or h < 0:
                raise CalibrationError(f"camera {name}: image size {w}×{h} is not positive", source)
        if self.baseline < 1e-9:
            raise CalibrationError("all cameras coincide (zero baseline): depth is unobservable", source)


def look_at(center: np.ndarray, target: np.ndarray, up: np.ndarray | tuple[float, float, float] = (0.0, -1.0, 0.0)
            ) -> tuple[np.ndarray, np.ndarray]:
    """World → camera ``(R, t)`` of a camera at ``center`` whose optical axis points at ``target``
    (OpenCV axes; ``up`` is the world direction that appears up in the image: −y by default)."""
    z = np.asarray(target, dtype=float) - np.asarray(center, dtype=float)
    z /= np.linalg.norm(z)
    x = np.cross(z, -np.asarray(up, dtype=float))
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    return R, -R @ np.asarray(center, dtype=float)


def ring_rig(n: int = 4, radius: float = 2.0, height: float = -0.8, size: tuple[int, int] = (640, 480),
             focal: float = 600.0, target: tuple[float, float, float] = (0.0, 0.0, 2.0)) -> Rig:
    """``n`` cameras evenly on a circle of ``radius`` (m) around ``target``, ``height`` m above it
    (y down: negative is up), all looking at it: the motion-capture layout around a working volume.
    Camera 0 sits on the −z side, so the world frame is close to today's stereo world (in front of
    camera 0 at ``target``'s depth); ``names`` are ``cam0…``."""
    K = np.array([[focal, 0.0, (size[0] - 1) / 2], [0.0, focal, (size[1] - 1) / 2], [0.0, 0.0, 1.0]])
    c = np.asarray(target, dtype=float)
    cams = []
    for k in range(n):
        a = 2 * math.pi * k / n
        R, t = look_at(c + np.array([radius * math.sin(a), height, -radius * math.cos(a)]), c)
        cams.append(Camera(K.copy(), R, t))
    return Rig(tuple(cams), tuple(f"cam{k}" for k in range(n)), ((int(size[0]), int(size[1])),) * n)


def _check_camera(cam: Camera, name: str, source: str | Path | None) -> None:
    if not np.all(np.isfinite(cam.K)) or abs(np.linalg.det(cam.K)) < 1e-12:
        raise CalibrationError(f"{name} camera matrix is singular or not finite", source)
    if not np.allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-6) or not np.all(np.isfinite(cam.t)):
        raise CalibrationError(f"{name} rotation is not orthonormal (or its translation is not finite)", source)


def triangulate_subset(rig: Rig | StereoRig, Y: np.ndarray, cams: np.ndarray) -> np.ndarray:
    """The homogeneous DLT (Hartley & Zisserman §12.2) of F frames' observations ``Y`` (F×2N)
    through the cameras ``cams`` only: rows ``u pⁱ³ᵀ − pⁱ¹ᵀ``, ``v pⁱ³ᵀ − pⁱ²ᵀ`` scaled to unit
    norm, solved for ``X / b`` (``b``: the rig's baseline, so that the answer does not depend on the
    length unit) and scaled back."""
    b = rig.baseline
    A = np.empty((len(Y), 2 * len(cams), 4))
    for k, c in enumerate(cams):
        cam = rig.cameras[c]
        P = cam.K @ np.hstack([cam.R, np.ravel(cam.t)[:, None] / b])
        A[:, 2 * k] = Y[:, 2 * c, None] * P[2] - P[0]
        A[:, 2 * k + 1] = Y[:, 2 * c + 1, None] * P[2] - P[1]
    A /= np.linalg.norm(A, axis=2, keepdims=True)
    Xh = np.linalg.svd(A)[2][:, -1]
    with np.errstate(divide="ignore", invalid="ignore"):
        X = Xh[:, :3] / Xh[:, 3:4] * b
    X[~np.isfinite(X).all(axis=1)] = np.nan
    return X


def triangulate_robust(rig: Rig | StereoRig, Y: np.ndarray, limit_px: float) -> tuple[np.ndarray, np.ndarray]:
    """Triangulation that drops the cameras whose rays disagree: for each frame, the largest subset
    of its observing cameras (≥ 2) whose DLT point lies in front of each of them and reprojects
    within ``limit_px`` in each; among subsets of that size, the one of least summed squared
    residual (the subset search of multi-camera tools, e.g. Nath et al.'s Anipose RANSAC
    triangulation, made exhaustive: N is small). Returns points (F×3, NaN where no subset agrees)
    and the cameras used (F×N booleans)."""
    from itertools import combinations

    Y = np.asarray(Y, dtype=float).reshape(-1, 2 * rig.n)
    F, n = len(Y), rig.n
    seen = np.isfinite(Y).reshape(F, n, 2).all(axis=2)
    X, used = np.full((F, 3), np.nan), np.zeros((F, n), dtype=bool)
    best = np.full(F, np.inf)
    for size in range(n, 1, -1):
        todo = ~used.any(axis=1) & (seen.sum(axis=1) >= size)
        for cams in combinations(range(n), size):
            rows = np.flatnonzero(todo & seen[:, list(cams)].all(axis=1))
            if not len(rows):
                continue
            Xs = triangulate_subset(rig, Y[rows], np.array(cams))
            err2 = np.stack([np.sum((rig.cameras[c].project(np.nan_to_num(Xs)) - Y[rows, 2 * c : 2 * c + 2]) ** 2, axis=1)
                             for c in cams], axis=1)
            front = np.stack([rig.cameras[c].depth(np.nan_to_num(Xs)) > 0 for c in cams], axis=1)
            ok = np.isfinite(Xs).all(axis=1) & front.all(axis=1) & (err2.max(axis=1) <= limit_px**2)
            better = ok & (err2.sum(axis=1) < best[rows])
            r = rows[better]
            X[r], best[r] = Xs[better], err2.sum(axis=1)[better]
            used[r] = False
            used[np.ix_(r, list(cams))] = True
    return X, used


def ray_distances(rig: Rig | StereoRig, X: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """Distance from each point ``X`` (F×3) to each camera's ray through its observation in ``Y``
    (F×2N undistorted pixels): F×N, NaN where a camera has none. Motion-capture systems report a
    reconstructed point's residual as these distances' mean (the C3D format's point residual)."""
    X, Y = np.asarray(X, dtype=float), np.asarray(Y, dtype=float)
    out = np.full((len(X), rig.n), np.nan)
    for c, cam in enumerate(rig.cameras):
        xy = cam.normalize(Y[:, 2 * c : 2 * c + 2])
        d = np.column_stack([xy, np.ones(len(xy))]) @ cam.R  # Rᵀ [x, y, 1] per row: the ray's direction
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        out[:, c] = np.linalg.norm(np.cross(X - cam.center, d), axis=1)
    return out
