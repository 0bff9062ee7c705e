"""Projected truth: when each camera exposes each frame, each marker's pixel coordinates and
visibility in both cameras at that camera's own time, and the ``truth.csv`` /
``target_truth.csv`` / ``timestamps.csv`` tables of the clip folder.

Times (the conventions of real rigs): camera c's frame k is exposed at ``k/fps`` plus, for the
right camera, the sync offset, plus a seeded jitter; that is the time row 0 is exposed, at the
middle of the exposure. With a rolling shutter, row r is exposed ``r · line_delay`` later, so a
marker imaged at row v is seen at ``t + v · line_delay`` — a fixed point in v, reached by
iterating (the delay moves the point by a small fraction of a pixel per step). Pixels are OpenCV's
projection with the lens distortion (``cv2.projectPoints``); the pinhole columns are the same point
without it, which is what undistorted detections are compared with.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.camera import Camera, StereoRig
from pipeline.core.clip import TARGET_TRUTH_COLUMNS, TIMESTAMP_COLUMNS, truth_columns, truth_extra_columns
from pipeline.core.io import write_csv
from pipeline.core.rig import Rig
from renderers.motion import Truth, distractor_positions
from renderers.scenario import Scenario

NEAR = 0.05  # metres; closer than this counts as not in front of the camera
#: rolling-shutter fixed-point iterations (each shrinks the error by ~|velocity·line_delay| in px/px)
RS_ITERATIONS = 4


@dataclass
class FrameTimes:
    """``t``: cameras × frames, when row 0 of each camera's frame is exposed (mid-exposure);
    ``present``: cameras × frames, False where the camera dropped the frame."""

    t: np.ndarray
    present: np.ndarray

    def footage_index(self, camera: int) -> np.ndarray:
        """Each present frame's index in that camera's video (dropped frames are not in it)."""
        return np.cumsum(self.present[camera]) - 1


def frame_times(scenario: Scenario) -> FrameTimes:
    """The clip's frame times and drops, seeded (``[seed, 40000 + camera]`` for jitter,
    ``[seed, 41000 + camera]`` for drops: turning one on never changes the other). Frame 0 is
    never dropped, so both videos start together."""
    n, rig = scenario.frames, scenario.rig
    base = np.arange(n) * scenario.dt
    t = np.stack([base + off for off in rig.time_offsets()])
    present = np.ones((rig.n_cameras, n), dtype=bool)
    for c in range(rig.n_cameras):
        if rig.jitter_s > 0:
            t[c] = t[c] + np.random.default_rng([scenario.seed, 40_000 + c]).normal(0.0, rig.jitter_s, n)
        rate = rig.camera_drop_rates()[c]
        if rate > 0:
            present[c] = np.random.default_rng([scenario.seed, 41_000 + c]).random(n) >= rate
            present[c, 0] = True
    return FrameTimes(t, present)


def seen_at(cam: Camera, truth: Truth, marker: int, t0: np.ndarray, line_delay: float, height: int) -> np.ndarray:
    """When ``cam`` sees ``marker`` in frames exposed from ``t0``: ``t0`` plus the rolling-shutter
    delay of the row that images it (a fixed point, iterated; rows clipped to the image)."""
    t = np.asarray(t0, dtype=float).copy()
    if line_delay <= 0:
        return t
    for _ in range(RS_ITERATIONS):
        X = truth.at(t, [marker])[0][:, 0]
        v = cam.project_distorted(X)[:, 1]
        t = t0 + np.clip(np.nan_to_num(v, nan=0.0), 0.0, height - 1.0) * line_delay
    return t


@dataclass
class ProjectedTruth:
    """``uv``: frames × markers × 4 (left u, v, right u, v) as the lenses image them;
    ``uv_pinhole``: the same without distortion; ``t_seen``: frames × markers × 2, when each
    camera saw each marker; ``visible``: frames × markers × 2; ``times``: the frame times."""

    uv: np.ndarray
    uv_pinhole: np.ndarray
    t_seen: np.ndarray
    visible: np.ndarray
    times: FrameTimes


def _occluders(scenario: Scenario, truth: Truth, t: np.ndarray,
               distractors: bool = True) -> list[tuple[np.ndarray, float, int | None]]:
    """Occluding spheres at times ``t`` (centre per frame, radius, marker index or None for distractors)."""
    pos = truth.at(t)[0]
    occ: list[tuple[np.ndarray, float, int | None]] = [(pos[:, i], float(truth.radii[i]), i) for i in range(len(truth.names))]
    dpos = distractor_positions(scenario, t)
    for j, d in enumerate(scenario.distractors if distractors else []):
        size = max(d.extents) if d.extents is not None else d.size
        r = size * (np.sqrt(3) / 2 if d.shape in ("cube", "box") else 0.5)
        occ.append((dpos[:, j], float(r), None))
    return occ


def _visible(rig: StereoRig | Rig, scenario: Scenario, truth: Truth, c: int, i: int, p: np.ndarray, uv: np.ndarray,
             t: np.ndarray, distractors: bool = True) -> np.ndarray:
    """In front of camera ``c``, inside the image, facing it (flat target markers) and not hidden
    behind another object (markers, distractors as bounding spheres unless the rendered image
    decides for them, the target plate)."""
    cam = rig.cameras[c]
    C = cam.center
    vis = (cam.depth(p) > NEAR) & rig.in_image(uv, camera=c)
    nrm = truth.at(t, [i])[2][:, 0]
    if np.all(np.isfinite(nrm)):
        vis &= np.einsum("ij,ij->i", nrm, C - p) > 0
    seg = p - C
    seg_len2 = np.einsum("ij,ij->i", seg, seg)
    for q, r, j in _occluders(scenario, truth, t, distractors):
        if j == i:
            continue
        s = np.clip(np.einsum("ij,ij->i", q - C, seg) / seg_len2, 0.0, 1.0)
        dist = np.linalg.norm(q - (C + s[:, None] * seg), axis=1)
        vis &= ~((dist < r + truth.radii[i]) & (s < 1.0 - 1e-9))
    for tp, tgt in zip(truth.target_paths, truth.targets, strict=True):
        if truth.names[i].startswith(tgt.name + "_"):
            continue  # the target's own markers lie on its face
        _, _, normal, center, _ = tp.points_at(t)
        denom = np.einsum("ij,ij->i", normal, seg)
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.einsum("ij,ij->i", normal, center - C) / denom
        hit = C + s[:, None] * seg
        inside = np.max(np.abs(hit - center), axis=1) < 1.4 * tgt.radius * 1.5  # conservative (plate is rotated)
        vis &= ~((s > 0) & (s < 1) & inside)
    return vis


def project_truth(rig: StereoRig | Rig, scenario: Scenario, truth: Truth, times: FrameTimes | None = None,
                  distractors: bool = True) -> ProjectedTruth:
    """Project every marker into both cameras, each at its own exposure time (sync offset, jitter,
    rolling shutter), and decide its visibility (dropped frames are not visible). ``distractors``:
    whether distractors hide markers here (as bounding spheres); False when a segmentation render
    decides instead."""
    times = times if times is not None else frame_times(scenario)
    n, m = truth.positions.shape[:2]
    N = len(rig.cameras)
    uv, uvp = np.empty((n, m, 2 * N)), np.empty((n, m, 2 * N))
    t_seen = np.empty((n, m, N))
    visible = np.zeros((n, m, N), dtype=bool)
    for c, cam in enumerate(rig.cameras):
        for i in range(m):
            t = seen_at(cam, truth, i, times.t[c], scenario.rig.line_delay_s, rig.sizes[c][1])
            p = truth.at(t, [i])[0][:, 0]
            t_seen[:, i, c] = t
            uv[:, i, 2 * c : 2 * c + 2] = cam.project_distorted(p)
            uvp[:, i, 2 * c : 2 * c + 2] = cam.project(p)
            vis = _visible(rig, scenario, truth, c, i, p, uv[:, i, 2 * c : 2 * c + 2], t, distractors)
            visible[:, i, c] = vis & times.present[c]
    return ProjectedTruth(uv, uvp, t_seen, visible, times)


def write_truth(path: Path, truth: Truth, proj: ProjectedTruth, cameras: tuple[str, ...] = ("left", "right"),
                groups: dict[str, str] | None = None) -> None:
    """Write ``truth.csv`` (long format, one row per frame per marker): the 3-D state at the first
    camera's frame time, each camera's pixels at its own time, visibility, the pinhole pixels, the
    times each camera saw the marker (columns named by ``cameras``) and the marker's group
    (``groups``: marker → the group a detector sees it as; its own name where absent)."""
    group = [(groups or {}).get(name) or name for name in truth.names]
    t_left = proj.times.t[0]
    pos, vel = (truth.positions, truth.velocities) if np.array_equal(t_left, truth.t) else truth.at(t_left)[:2]

    def rows():
        for k in range(truth.n_frames):
            for i, name in enumerate(truth.names):
                yield (
                    k, t_left[k], name, *pos[k, i], *vel[k, i],
                    *proj.uv[k, i], *proj.visible[k, i].astype(int).tolist(),
                    *proj.uv_pinhole[k, i], *proj.t_seen[k, i], group[i],
                )

    write_csv(path, truth_columns(cameras) + truth_extra_columns(cameras), rows())


def write_timestamps(path: Path, times: FrameTimes, fmt: str, cameras: tuple[str, ...] = ("left", "right")) -> None:
    """``timestamps.csv``: per camera, each frame of its footage (numbered as the footage numbers
    it: a video's position, a PNG's file number) and the time its row 0 was exposed."""

    def rows():
        for c, cam in enumerate(cameras):
            index = times.footage_index(c) if fmt == "mp4" else np.arange(times.t.shape[1])
            for k in np.flatnonzero(times.present[c]):
                yield (int(index[k]), cam, times.t[c, k])

    write_csv(path, TIMESTAMP_COLUMNS, rows())


def write_target_truth(path: Path, truth: Truth, proj: ProjectedTruth) -> None:
    """Write ``target_truth.csv`` for the (single) four-point target."""
    tgt = truth.targets[0]
    idx = [truth.names.index(f"{tgt.name}_{j}") for j in range(1, 5)]
    t_left = proj.times.t[0]
    if np.array_equal(t_left, truth.t):
        al, zz = np.column_stack([tgt.alpha, tgt.alpha_dot]), np.column_stack([tgt.distance, tgt.distance_dot])
    else:  # jittered frame times: the state at the left camera's time, as truth.csv
        al, zz = truth.target_paths[0].state_at(t_left)

    def rows():
        for k in range(truth.n_frames):
            px = [proj.uv[k, i, 2 * c + d] for c in range(2) for i in idx for d in range(2)]
            yield (k, t_left[k], al[k, 0], al[k, 1], zz[k, 0], zz[k, 1], tgt.axis_angle, *px)

    write_csv(path, TARGET_TRUTH_COLUMNS, rows())
