"""Calibration boards rendered for a known rig: image pairs of a chessboard or ChArUco board in many
poses, with the rig that made them as the truth ``stereotrack calibrate`` must recover.

A plane needs no rasteriser: each pixel (sampled ``SUPERSAMPLE``² times) is a ray through the
camera's exact model — ``cv2.undistortPoints`` inverts the lens distortion, so distorted rigs are
drawn exactly — intersected with the board's plane, and the board's texture is looked up where it
lands. The same camera model (:class:`pipeline.core.camera.Camera`) renders the clips and reads them.
"""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.board import Board
from pipeline.core.camera import UNDISTORT_CRITERIA, Camera, StereoRig
from pipeline.core.io import atomic_path, ensure_dir

SUPERSAMPLE = 3  # samples per pixel and axis (anti-aliasing of the square edges)
BACKGROUND = 110  # grey level around the board


def _rays(cam: Camera, size: tuple[int, int]) -> np.ndarray:
    """Unit-less ray directions (camera frame, z = 1) of every sub-pixel sample: H·S × W·S × 3."""
    w, h = size
    s = SUPERSAMPLE
    offs = (np.arange(s) + 0.5) / s - 0.5
    u = (np.arange(w)[:, None] + offs[None]).ravel()
    v = (np.arange(h)[:, None] + offs[None]).ravel()
    uu, vv = np.meshgrid(u, v)
    pts = np.stack([uu.ravel(), vv.ravel()], axis=1).reshape(-1, 1, 2)
    xy = cv2.undistortPoints(pts, cam.K, np.asarray(cam.D, dtype=float), criteria=UNDISTORT_CRITERIA).reshape(-1, 2)
    return np.column_stack([xy, np.ones(len(xy))]).reshape(h * s, w * s, 3)


def render_view(cam: Camera, rays: np.ndarray, board: Board, texture: np.ndarray, pose: tuple[np.ndarray, np.ndarray],
                noise: float, rng: np.random.Generator) -> np.ndarray:
    """One camera's grey image of the board at ``pose`` (board → world rotation and the world
    position of its top-left outer corner), averaged over the sub-pixel samples."""
    Rb, tb = pose
    # the board plane seen through the camera is a homography: a ray r ∝ M (u, v, 1) with
    # M = [R Rb₁ | R Rb₂ | R tb + t], so (u, v, w) = M⁻¹ r, in front of the camera where w > 0
    M = np.column_stack([cam.R @ Rb[:, 0], cam.R @ Rb[:, 1], cam.R @ tb + np.ravel(cam.t)])
    uvw = rays.reshape(-1, 3) @ np.linalg.inv(M).T.astype(rays.dtype)
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = uvw[:, :2] / uvw[:, 2:]
    W, H = board.size
    th, tw = texture.shape
    inside = (uvw[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    val = np.full(len(uvw), float(BACKGROUND))
    px = np.clip((uv[inside, 0] / W * tw).astype(int), 0, tw - 1)
    py = np.clip((uv[inside, 1] / H * th).astype(int), 0, th - 1)
    val[inside] = 40.0 + 175.0 * texture[py, px] / 255.0  # printed black and white under light
    s = SUPERSAMPLE
    h, w = rays.shape[0] // s, rays.shape[1] // s
    img = val.reshape(h, s, w, s).mean(axis=(1, 3)) + rng.normal(0.0, noise, (h, w))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


def random_pose(rig: StereoRig, board: Board, rng: np.random.Generator, depth: tuple[float, float]) -> tuple:
    """A board pose in view of both cameras: centre at a random depth and image position, tilted up
    to 35° and turned up to 25° in its plane; redrawn until every outer corner is inside both
    images with a 5 % margin."""
    W, H = board.size
    w, h = rig.image_size
    corners = np.array([[0, 0, 0], [W, 0, 0], [W, H, 0], [0, H, 0]], dtype=float)
    for _ in range(1000):
        z = rng.uniform(*depth)
        cx, cy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.9) * h
        centre = rig.left.R.T @ (np.linalg.inv(rig.left.K) @ [cx, cy, 1.0] * z - rig.left.t)
        tilt = np.radians(rng.uniform(-35, 35, 2))
        spin = math.radians(rng.uniform(-25, 25))
        Rb = rig.left.R.T @ _rotation(tilt[0], tilt[1], spin)  # board axes: x right, y down, z away from the camera
        tb = centre - Rb @ [W / 2, H / 2, 0.0]
        world = corners @ Rb.T + tb
        ok = all(_inside(cam, world, w, h) for cam in rig.cameras)
        if ok:
            return Rb, tb
    raise RuntimeError("no board pose fits both views: the board is too large for this rig")


def _rotation(ax: float, ay: float, az: float) -> np.ndarray:
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rx @ Ry @ Rz


def _inside(cam: Camera, X: np.ndarray, w: int, h: int) -> bool:
    if np.any(cam.depth(X) <= 0.05):
        return False
    uv = cam.project_distorted(X)
    m = 0.05
    return bool(np.all((uv[:, 0] > m * w) & (uv[:, 0] < (1 - m) * w) & (uv[:, 1] > m * h) & (uv[:, 1] < (1 - m) * h)))


def render_board_pairs(rig: StereoRig, board: Board, out_dir: str | Path, pairs: int = 15, seed: int = 0,
                       depth: tuple[float, float] = (0.5, 1.1), noise: float = 2.0) -> list[Path]:
    """``pairs`` image pairs ``left_NN.png`` / ``right_NN.png`` of ``board`` in random poses seen by
    both cameras of ``rig`` (its distortion included), written to ``out_dir``; the paths written."""
    out = ensure_dir(out_dir)
    rng = np.random.default_rng(seed)
    tex = board.texture()
    rays = [_rays(cam, rig.image_size) for cam in rig.cameras]
    written = []
    for k in range(pairs):
        pose = random_pose(rig, board, rng, depth)
        for name, cam, r in zip(("left", "right"), rig.cameras, rays, strict=True):
            path = out / f"{name}_{k + 1:02d}.png"
            with atomic_path(path) as tmp:
                cv2.imwrite(str(tmp), render_view(cam, r, board, tex, pose, noise, rng))
            written.append(path)
    return written
