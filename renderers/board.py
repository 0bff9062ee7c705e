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
from pipeline.core.rig import Rig

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


def view_pose(rig: Rig, board: Board, rng: np.random.Generator, centre: np.ndarray, spread: float) -> tuple:
    """A board pose for an N-camera rig: centre within ``spread`` m of ``centre``, facing the mean
    direction of one camera or two neighbours (chosen at random) within 25°, turned in its plane."""
    W, H = board.size
    n = rig.n
    first = int(rng.integers(n))
    chosen = [first, (first + 1) % n] if rng.random() < 0.6 else [first]
    c = np.asarray(centre, dtype=float) + rng.uniform(-spread, spread, 3)
    toward = np.mean([(rig.cameras[k].center - c) / np.linalg.norm(rig.cameras[k].center - c) for k in chosen], axis=0)
    toward /= np.linalg.norm(toward)
    z = -toward  # the board's z axis points away from the cameras that see its face
    x = np.cross(rig.cameras[first].R[1], z)  # level with the first camera's image rows
    x /= np.linalg.norm(x)
    Rb = np.column_stack([x, np.cross(z, x), z]) @ _rotation(*np.radians(rng.uniform(-25, 25, 3)))
    return Rb, c - Rb @ [W / 2, H / 2, 0.0]


def _sees(cam: Camera, board: Board, pose: tuple, size: tuple[int, int]) -> bool:
    """Whether ``cam`` sees the board's printed face, every outer corner inside its image (5 %
    margin), at less than 70° from face-on."""
    Rb, tb = pose
    W, H = board.size
    corners = np.array([[0, 0, 0], [W, 0, 0], [W, H, 0], [0, H, 0]], dtype=float) @ Rb.T + tb
    centre = corners.mean(axis=0)
    ray = (cam.center - centre) / np.linalg.norm(cam.center - centre)
    return bool(-ray @ Rb[:, 2] > math.cos(math.radians(70))) and _inside(cam, corners, *size)


def close_pose(rig: Rig, c: int, board: Board, rng: np.random.Generator, depth: tuple[float, float]) -> tuple:
    """A pose filling much of camera ``c``'s view (as :func:`random_pose` draws for a stereo pair):
    what a user shows one camera to calibrate its lens."""
    pair = StereoRig(rig.cameras[c], rig.cameras[(c + 1) % rig.n], rig.sizes[c])
    one = StereoRig(pair.left, pair.left, pair.image_size)
    return random_pose(one, board, rng, depth)


def render_board_views(rig: Rig, board: Board, out_dir: str | Path, views: int = 30, seed: int = 0,
                       centre: tuple[float, float, float] = (0.0, 0.0, 2.15), spread: float = 0.3,
                       noise: float = 2.0, close: int = 0, close_depth: tuple[float, float] = (0.8, 1.4)
                       ) -> dict[str, list[Path]]:
    """``views`` poses of ``board`` around ``centre`` (the first camera's frame), each rendered by
    every camera of ``rig`` that sees its face — any subset, at least one — as
    ``out_dir/<camera>/NN.png`` (the same number in every camera that saw it: simultaneous); then
    ``close`` poses per camera ``close_depth`` m in front of it (its lens calibration), numbered on."""
    out = ensure_dir(out_dir)
    rng = np.random.default_rng(seed)
    tex = board.texture()
    rays = [_rays(cam, size) for cam, size in zip(rig.cameras, rig.sizes, strict=True)]
    written: dict[str, list[Path]] = {name: [] for name in rig.names}
    k = 0
    plan = [None] * views + [c for c in range(rig.n) for _ in range(close)]
    while k < len(plan):
        c0 = plan[k]
        pose = (view_pose(rig, board, rng, np.asarray(centre), spread) if c0 is None
                else close_pose(rig, c0, board, rng, close_depth))
        seen = [c for c in range(rig.n) if _sees(rig.cameras[c], board, pose, rig.sizes[c])]
        if not seen:
            continue
        k += 1
        for c in seen:
            path = ensure_dir(out / rig.names[c]) / f"{k:02d}.png"
            with atomic_path(path) as tmp:
                cv2.imwrite(str(tmp), render_view(rig.cameras[c], rays[c], board, tex, pose, noise, rng))
            written[rig.names[c]].append(path)
    return written
