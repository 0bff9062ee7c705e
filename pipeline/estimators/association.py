"""Many identical markers: which detection belongs to which track, over any number of cameras.

Each frame the association (1) predicts every live track with a constant-velocity Kalman filter
(Bar-Shalom, Li & Kirubarajan §6.2.2) and projects it into each camera with the camera model's
Jacobian, ``S = J P Jᵀ + σ² I``; (2) assigns each camera's detections to the tracks as a whole
(global nearest neighbour: :func:`scipy.optimize.linear_sum_assignment` on the negative
log-likelihood ``rᵀ S⁻¹ r + ln det S`` gated at the χ²₂ quantile), the cameras in turn, each
camera's assignment using the detections the earlier cameras gave the tracks this frame (the
sequential corrector), so a look-alike that lies on one camera's epipolar line but not where the
other cameras put the track is not taken; (3) starts tentative tracks from detections left over in
two cameras that agree epipolarly (Hartley & Zisserman §9.2) and triangulate in front of both,
confirms a track after ``confirm_hits`` of ``confirm_window`` frames, lets a confirmed track coast
through ``max_coast`` frames without a detection and ends it then, or when its position's
uncertainty grows past ``max_position_sigma``.

The result is each confirmed track's own observation stream (frames × 2·cameras pixels, NaN where it
had no detection): any registered point estimator then filters it (``run``), so one association
serves every filter. Two baselines share the harness: ``mode="greedy"`` lets tracks take their
best gated detection one track after another, and ``mode="epipolar"`` matches each frame on its
own (Hungarian on the epipolar distance) and links the frames' points by nearest neighbour.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.core.camera import Camera, StereoRig, epipolar_distances, triangulate_views
from pipeline.core.lazy import lazy_module
from pipeline.core.rig import Rig
from pipeline.estimators.base import Track, transition, white_noise_acceleration
from pipeline.estimators.registration import create

if TYPE_CHECKING:
    from scipy import optimize, special
else:  # imported on first use: scipy costs a batch worker ~0.25 s, and only identical markers need it
    optimize, special = lazy_module("scipy.optimize"), lazy_module("scipy.special")

Mode = Literal["gnn", "greedy", "epipolar"]
INFEASIBLE = 1e9  # an assignment cost that means "not this pair"


class AssociationConfig(BaseModel):
    """How tracks are predicted, gated, started, confirmed and ended."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    pixel_sigma: float = Field(1.0, gt=0)
    """detection noise (px) of every camera"""
    process_noise: float = Field(0.5, gt=0)
    """spectral density q (m²/s³) of the prediction's white-noise acceleration"""
    gate: float = Field(0.9999, gt=0, lt=1)
    """χ²₂ quantile a detection's normalized innovation must stay under to be assigned to a track"""
    birth_gate_sigmas: float = Field(3.0, gt=0)
    """two cameras' leftover detections start a track when their epipolar distance is under this many σ"""
    confirm_hits: int = Field(3, ge=1)
    """frames with a detection, within ``confirm_window``, that confirm a tentative track"""
    confirm_window: int = Field(4, ge=1)
    max_coast: int = Field(10, ge=0)
    """frames a confirmed track predicts without a detection before it ends"""
    max_position_sigma: float = Field(0.5, gt=0)
    """a track whose predicted position σ (m, largest axis) grows past this ends"""
    start_velocity_sigma: float = Field(2.0, gt=0)
    """σ (m/s) of a new track's velocity (it starts at rest)"""
    merge_px: float = Field(4.0, ge=0)
    """two tracks whose images lie closer than this (px) and share fewer detections than they are
    were merged into one blob: neither updates from it in that camera"""
    merged_sigma: float = Field(4.0, gt=0)
    """spread (px) of a blob of merged images about each marker's own image: the noise added when a
    track that found no blob of its own updates from a merged one"""
    link_distance: float = Field(0.3, gt=0)
    """the epipolar baseline's largest 3-D step (m) between frames that links two points"""


@dataclass
class _Track:
    """One track while the association runs: its state, its detections so far and its history."""

    x: np.ndarray
    P: np.ndarray
    born: int
    obs: list[np.ndarray] = field(default_factory=list)  # per frame since birth: 2·cameras pixels
    hits: deque = field(default_factory=lambda: deque(maxlen=64))
    coasted: int = 0
    covered: bool = False  # this frame: updated from a blob of merged images only
    number: int | None = None  # given at confirmation, in order, never reused

    def position_sigma(self) -> float:
        return float(np.sqrt(np.max(np.diag(self.P)[:3])))


@dataclass
class Association:
    """The outcome: each confirmed track's observations (frames × 2·cameras, NaN outside its life)
    and the frames it was born and ended at (``end`` exclusive)."""

    observations: dict[int, np.ndarray]
    born: dict[int, int]
    ended: dict[int, int]


def associate(cameras: list[Camera], dt: float, detections: list[list[np.ndarray]],
              config: AssociationConfig | None = None, mode: Mode = "gnn",
              merged: list[list[np.ndarray]] | None = None) -> Association:
    """Associate ``detections`` (per frame, per camera: k × 2 undistorted pixels) into tracks.
    ``merged`` (beside them: k flags) marks blobs of several markers' merged images (the detect
    stage's ``merged`` column): such a blob is no one's position, so it is assigned to no track,
    goes into no track's observations and starts no track; a track it covers is only held near it
    with widened noise (:meth:`_Run._covered`) until their images part."""
    cfg = config or AssociationConfig()
    if mode == "epipolar":
        return _epipolar_baseline(cameras, detections, cfg)
    run = _Run(cameras, dt, cfg, mode)
    for k, frame in enumerate(detections):
        run.frame(k, frame, merged[k] if merged is not None and k < len(merged) else None)
    return run.finish(len(detections))


class _Run:
    """The state of one association over a clip (tracks alive and ended)."""

    def __init__(self, cameras: list[Camera], dt: float, cfg: AssociationConfig, mode: Mode) -> None:
        self.cameras, self.cfg, self.mode = cameras, cfg, mode
        self.A, self.Q = transition(dt), white_noise_acceleration(dt, cfg.process_noise)
        self.R = np.eye(2) * cfg.pixel_sigma**2
        self.threshold = float(special.chdtri(2, 1.0 - cfg.gate))
        self.live: list[_Track] = []
        self.done: list[tuple[_Track, int]] = []
        self.count = 0

    def frame(self, k: int, frame: list[np.ndarray], merged: list[np.ndarray] | None = None) -> None:
        """Predict, assign camera by camera, start tracks from what is left, manage the tracks;
        ``merged`` flags (per camera) mark blobs that no track updates from and none starts from."""
        for t in self.live:
            t.x, t.P = self.A @ t.x, self.A @ t.P @ self.A.T + self.Q
            t.obs.append(np.full(2 * len(self.cameras), np.nan))
        left = []
        frame = [np.asarray(d, dtype=float).reshape(-1, 2) for d in frame]
        whole = [np.ones(len(d), dtype=bool) if merged is None or len(merged[c]) != len(d) else ~np.asarray(merged[c], bool)
                 for c, d in enumerate(frame)]
        for c, dets in enumerate(frame):
            ahead = frame[c + 1][whole[c + 1]] if c + 1 < len(frame) and self.mode == "gnn" else None
            near = self._assign(c, dets, ahead, whole[c]) if self.live and len(dets) else set()
            left.append(np.array([d for j, d in enumerate(dets) if j not in near and whole[c][j]]).reshape(-1, 2))
        self._births(k, left)
        self._manage(k)

    def _assign(self, c: int, dets: np.ndarray, ahead: np.ndarray | None, whole: np.ndarray) -> set[int]:
        """Camera ``c``'s detections to the live tracks, each assigned detection applied to its track
        at once (the next camera sees the update); returns the detections inside some track's gate,
        assigned or not (a blob two tracks share, or a track's second blob, starts no new track).
        With ``ahead`` (the next camera's detections) a pairing's cost adds the best the next camera
        offers the track once updated with it: a look-alike that fits this camera but leaves the
        track nothing consistent in the next is not taken."""
        cam = self.cameras[c]
        X = np.array([t.x for t in self.live])
        h, J, S = self._predicted_all(cam, X)  # every live track at once: T × 2, T × 2 × 3, T × 2 × 2
        r = dets[None, :, :] - h[:, None, :]
        Si = np.linalg.inv(S)
        nis = np.einsum("tdi,tij,tdj->td", r, Si, r)
        gated = (nis < self.threshold) & np.isfinite(h[:, :1])
        cost = np.where(gated, nis + np.log(np.linalg.det(S))[:, None], INFEASIBLE)
        K, Pn = self._gains(J, Si)
        if ahead is not None and gated.any():
            ti, dj = np.nonzero(gated)
            moved = X[ti, :3] + np.einsum("kab,kb->ka", K[ti, :3], dets[dj] - h[ti])  # each pairing's updated position
            cost[ti, dj] += self._best_next(c + 1, moved, Pn[ti], ahead)
        near = {int(j) for j in np.flatnonzero((cost < INFEASIBLE).any(axis=0))}
        if self.mode == "gnn":
            cost[_merged_tracks(h, cost, self.cfg.merge_px)] = INFEASIBLE
        cost[:, ~whole] = INFEASIBLE  # a blob flagged merged updates no one (it still starts no track)
        pairs = _greedy(cost) if self.mode == "greedy" else _hungarian(cost)
        for i, d in pairs.items():  # the Kalman update (Joseph form), its gain and covariance made above
            t = self.live[i]
            t.x, t.P = X[i] + K[i] @ (dets[d] - h[i]), Pn[i]
            t.obs[-1][2 * c : 2 * c + 2] = dets[d]
        if not whole.all():
            self._covered(np.setdiff1d(np.arange(len(self.live)), list(pairs)), X, h, J, S, dets[~whole])
        return near

    def _covered(self, free: np.ndarray, X: np.ndarray, h: np.ndarray, J: np.ndarray, S: np.ndarray,
                 blobs: np.ndarray) -> None:
        """Tracks that took no detection in this camera but lie under a blob of merged images: each
        is updated from the nearest such blob in its gate with the blob's spread added to the noise
        (``merged_sigma``), which keeps it alive and near its marker through the merge without
        pulling its velocity to the blob's centroid; the blob goes into no track's observations,
        so the filters behind the association coast in this camera."""
        extra = np.eye(2) * self.cfg.merged_sigma**2
        for i in free:
            if not np.isfinite(h[i]).all():
                continue
            Sm = S[i] + extra
            r = blobs - h[i]
            nis = np.einsum("ki,ij,kj->k", r, np.linalg.inv(Sm), r)
            if nis.min() >= self.threshold:
                continue
            t, H = self.live[i], np.hstack([J[i], np.zeros((2, 3))])
            Kg = t.P @ H.T @ np.linalg.inv(Sm)
            IKH = np.eye(6) - Kg @ H
            t.x = X[i] + Kg @ r[int(np.argmin(nis))]
            t.P = IKH @ t.P @ IKH.T + Kg @ (self.R + extra) @ Kg.T
            t.covered = True

    def _gains(self, J: np.ndarray, Si: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Every live track's Kalman gain for one camera (T × 6 × 2) and its covariance once updated
        with a detection there, in Joseph form (T × 6 × 6): neither depends on which detection."""
        P = np.array([t.P for t in self.live])
        H = np.zeros((len(self.live), 2, 6))
        H[:, :, :3] = J
        K = P @ H.transpose(0, 2, 1) @ Si
        IKH = np.eye(6) - K @ H
        return K, IKH @ P @ IKH.transpose(0, 2, 1) + K @ self.R @ K.transpose(0, 2, 1)

    def _predicted_all(self, cam: Camera, X: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The states ``X``' (T × 6) predicted pixels in a camera (NaN behind it), position Jacobians
        and innovation covariances ``S = J P_pp Jᵀ + R`` (the velocity does not enter the projection)."""
        P = np.array([t.P[:3, :3] for t in self.live])
        h, J = cam.project(X[:, :3]), cam.jacobian(X[:, :3])
        h[cam.depth(X[:, :3]) <= 0] = np.nan
        return h, J, J @ P @ J.transpose(0, 2, 1) + self.R

    def _best_next(self, nxt: int, X: np.ndarray, Pn: np.ndarray, ahead: np.ndarray) -> np.ndarray:
        """For each candidate pairing, the track's position once updated with the detection (``X``,
        k × 3) and covariance (``Pn``, k × 6 × 6): the negative log-likelihood of camera ``nxt``'s best
        gated detection (a miss: the gate's value); 0 where the point is behind that camera."""
        cam = self.cameras[nxt]
        hn, Jn = cam.project(X), cam.jacobian(X)
        Sn = Jn @ Pn[:, :3, :3] @ Jn.transpose(0, 2, 1) + self.R
        best = np.full(len(X), self.threshold)
        if len(ahead):
            r = ahead[None, :, :] - hn[:, None, :]
            best = np.minimum(np.einsum("kni,kij,knj->kn", r, np.linalg.inv(Sn), r).min(axis=1), self.threshold)
        out = best + np.log(np.linalg.det(Sn))
        return np.where(cam.depth(X) > 0, out, 0.0)

    def _births(self, k: int, left: list[np.ndarray]) -> None:
        """Tentative tracks from leftover detections that two cameras agree on."""
        for X, obs in _stereo_points(self.cameras, left, self.cfg.birth_gate_sigmas * self.cfg.pixel_sigma):
            P = np.diag([*([_start_position_var(self.cameras, X, self.cfg.pixel_sigma)] * 3),
                         *([self.cfg.start_velocity_sigma**2] * 3)])
            t = _Track(np.r_[X, 0.0, 0.0, 0.0], P, k)
            t.obs.append(obs)
            self.live.append(t)

    def _manage(self, k: int) -> None:
        """Hits and coasting counted; tentative tracks confirmed or dropped; lost tracks ended."""
        keep = []
        for t in self.live:
            hit, t.covered = bool(np.isfinite(t.obs[-1]).any()) or t.covered, False
            t.hits.append(hit)
            t.coasted = 0 if hit else t.coasted + 1
            if t.number is None and sum(list(t.hits)[-self.cfg.confirm_window :]) >= self.cfg.confirm_hits:
                t.number, self.count = self.count, self.count + 1
            lost = t.coasted > self.cfg.max_coast or t.position_sigma() > self.cfg.max_position_sigma
            tentative_failed = t.number is None and len(t.hits) >= self.cfg.confirm_window
            if lost or tentative_failed:
                if t.number is not None:
                    self.done.append((t, k + 1 - t.coasted))
                continue
            keep.append(t)
        self.live = keep

    def finish(self, n: int) -> Association:
        """Every confirmed track's observations over the clip's ``n`` frames."""
        ended = self.done + [(t, n - t.coasted) for t in self.live if t.number is not None]
        out = Association({}, {}, {})
        for t, end in ended:
            Y = np.full((n, 2 * len(self.cameras)), np.nan)
            Y[t.born : t.born + len(t.obs)] = np.array(t.obs)
            Y[end:] = np.nan
            assert t.number is not None
            out.observations[t.number], out.born[t.number], out.ended[t.number] = Y, t.born, end
        return out


def _merged_tracks(where: np.ndarray, cost: np.ndarray, merge_px: float) -> np.ndarray:
    """Tracks whose images lie within ``merge_px`` of another's and that, together, gate fewer
    detections than they are: their blobs have merged, and a merged blob is no one's position (the
    tracks coast in this camera until their images part)."""
    out = np.zeros(len(where), dtype=bool)
    d = np.linalg.norm(where[:, None] - where[None], axis=2)
    close = (d < merge_px) & ~np.eye(len(where), dtype=bool)
    for i in np.flatnonzero(close.any(axis=1)):
        group = np.flatnonzero(close[i] | (np.arange(len(where)) == i))
        if (cost[group] < INFEASIBLE).any(axis=0).sum() < len(group):
            out[group] = True
    return out


def _hungarian(cost: np.ndarray) -> dict[int, int]:
    r, c = optimize.linear_sum_assignment(cost)
    return {int(a): int(b) for a, b in zip(r, c, strict=True) if cost[a, b] < INFEASIBLE}


def _greedy(cost: np.ndarray) -> dict[int, int]:
    """The baseline: each track in turn takes its cheapest feasible detection not taken yet."""
    taken: dict[int, int] = {}
    for i in range(cost.shape[0]):
        free = [j for j in np.argsort(cost[i]) if cost[i, j] < INFEASIBLE and j not in taken.values()]
        if free:
            taken[i] = int(free[0])
    return taken


def _stereo_points(cameras: list[Camera], dets: list[np.ndarray], gate_px: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """3-D points from detections two cameras agree on: the first two cameras' detections matched
    by Hungarian on the epipolar distance (under ``gate_px``), triangulated in front of both, each
    other camera's detection added where it reprojects within the gate. (point, observation row)."""
    if len(cameras) < 2 or not len(dets[0]) or not len(dets[1]):
        return []
    D = epipolar_distances(cameras[0], cameras[1], dets[0], dets[1])
    out = []
    for i, j in _hungarian(np.where(D < gate_px, D, INFEASIBLE)).items():
        obs = np.full(2 * len(cameras), np.nan)
        obs[0:2], obs[2:4] = dets[0][i], dets[1][j]
        X = triangulate_views(cameras, obs)
        if not np.all(np.isfinite(X)) or any(cam.depth(X[None])[0] <= 0 for cam in cameras[:2]):
            continue
        for c in range(2, len(cameras)):
            if len(dets[c]) and cameras[c].depth(X[None])[0] > 0:
                d = np.linalg.norm(dets[c] - cameras[c].project(X[None])[0], axis=1)
                if d.min() < gate_px:
                    obs[2 * c : 2 * c + 2] = dets[c][int(np.argmin(d))]
        out.append((X, obs))
    return out


def _start_position_var(cameras: list[Camera], X: np.ndarray, sigma: float) -> float:
    """A new track's position variance: the triangulated point's, ``σ² (JᵀJ)⁻¹``'s largest diagonal
    term over the first two cameras (depth is the poorly known direction)."""
    J = np.vstack([cam.jacobian(X[None])[0] for cam in cameras[:2]])
    return float(sigma**2 * np.max(np.diag(np.linalg.inv(J.T @ J))))


def _epipolar_baseline(cameras: list[Camera], detections: list[list[np.ndarray]],
                       cfg: AssociationConfig) -> Association:
    """The per-frame baseline: each frame's points from :func:`_stereo_points`, linked to the tracks'
    last points by Hungarian on the 3-D distance (under ``link_distance``); a point left unlinked
    starts a track, a track unlinked for more than ``max_coast`` frames ends."""
    n = len(detections)
    tracks: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
    last: dict[int, np.ndarray] = {}
    seen: dict[int, int] = {}
    for k, frame in enumerate(detections):
        last = {i: X for i, X in last.items() if k - seen[i] <= cfg.max_coast + 1}
        pts = _stereo_points(cameras, [np.asarray(d, float).reshape(-1, 2) for d in frame],
                             cfg.birth_gate_sigmas * cfg.pixel_sigma)
        ids = list(last)
        D = np.array([[np.linalg.norm(last[i] - X) for X, _ in pts] for i in ids]).reshape(len(ids), len(pts))
        links = _hungarian(np.where(D < cfg.link_distance, D, INFEASIBLE))
        now = {}
        for a, b in links.items():
            now[ids[a]] = b
        for b in set(range(len(pts))) - set(now.values()):
            now[len(tracks)] = b
            tracks[len(tracks)] = []
        for i, b in now.items():
            tracks[i].append((k, *pts[b]))
            last[i], seen[i] = pts[b][0], k
    out = Association({}, {}, {})
    for i, rows in tracks.items():
        Y = np.full((n, 2 * len(cameras)), np.nan)
        for k, _, obs in rows:
            Y[k] = obs
        out.observations[i], out.born[i], out.ended[i] = Y, rows[0][0], rows[-1][0] + 1
    return out


def track_group(rig: StereoRig | Rig, dt: float, detections: list[list[np.ndarray]], method: str = "ekf",
                group: str = "marker", config: AssociationConfig | None = None,
                method_config: dict | None = None, mode: Mode = "gnn") -> dict[str, Track]:
    """A group of identical markers seen by a stereo rig: the association's tracks (``<group>#<n>``,
    numbered from 1 in order of confirmation), each filtered by the registered point ``method``
    from its own observations, NaN before its birth and after its end."""
    return filter_tracks(rig, dt, associate(list(rig.cameras), dt, detections, config, mode), method, group,
                         method_config)


def filter_tracks(rig: StereoRig | Rig, dt: float, assoc: Association, method: str, group: str = "marker",
                  method_config: dict | None = None) -> dict[str, Track]:
    """Each associated track filtered by ``method`` from its own observations (``<group>#<n>``),
    NaN before its birth and after its end: one association, any filter."""
    out = {}
    for number, Y in assoc.observations.items():
        tr = create(method, rig, dt, method_config).run(Y)
        life = np.zeros(len(Y), dtype=bool)
        life[assoc.born[number] : assoc.ended[number]] = True
        tr.position[~life], tr.velocity[~life] = np.nan, np.nan
        out[f"{group}#{number + 1}"] = tr
    return out
