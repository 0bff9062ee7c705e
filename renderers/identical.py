"""Identical markers without images: smooth random paths that cross in a working volume, and what a
perfect blob detector would report of them in each camera (the projections with Gaussian noise,
shuffled, with no identity), including what makes identical markers hard: images that merge into
one blob, detections that drop out, markers that leave the view. For the association's tests and
benchmark, where rendering would add time but no information."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import Camera

#: the working volume (m, the first camera's frame): centre and half-size
VOLUME_CENTRE = np.array([0.0, 0.0, 2.6])
VOLUME_HALF = np.array([0.55, 0.35, 0.8])


def crossing_paths(markers: int, frames: int, fps: float, seed: int, speed: float = 0.6) -> np.ndarray:
    """frames × markers × 3 positions: each marker a sum of two sinusoids per axis with random
    frequencies and phases, scaled to fill :data:`VOLUME_HALF` and move at about ``speed`` m/s,
    so that paths cross (and pass along each other's epipolar lines) many times a minute."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    out = np.empty((frames, markers, 3))
    for m in range(markers):
        w = rng.uniform(0.3, 1.2, (2, 3)) * speed / VOLUME_HALF.mean()  # rad/s
        phase = rng.uniform(0, 2 * np.pi, (2, 3))
        share = rng.uniform(0.3, 0.7, 3)
        wave = share * np.sin(w[0] * t[:, None] + phase[0]) + (1 - share) * np.sin(w[1] * t[:, None] + phase[1])
        out[:, m] = VOLUME_CENTRE + VOLUME_HALF * wave
    return out


def detections(cameras: list[Camera], positions: np.ndarray, sigma: float, seed: int, image_size: tuple[int, int],
               drop: float = 0.02, merge_px: float = 3.0) -> list[list[np.ndarray]]:
    """Per frame, per camera, the detections (k × 2 px, shuffled) of ``positions`` (frames × markers
    × 3): projections with noise ``sigma`` inside the image, a random ``drop`` of them missed, and
    projections closer than ``merge_px`` reported as one blob at their mean."""
    return labelled_detections(cameras, positions, sigma, seed, image_size, drop, merge_px)[0]


def labelled_detections(cameras: list[Camera], positions: np.ndarray, sigma: float, seed: int,
                        image_size: tuple[int, int], drop: float = 0.02, merge_px: float = 3.0
                        ) -> tuple[list[list[np.ndarray]], list[list[list[tuple[int, ...]]]]]:
    """:func:`detections` and, beside each detection, the markers it is the image of (one, or
    several for a merged blob): what a perfect association would know."""
    rng = np.random.default_rng(seed)
    w, h = image_size
    out, labels = [], []
    for X in positions:
        frame, frame_labels = [], []
        for cam in cameras:
            uv = cam.project(X) + rng.normal(0, sigma, (len(X), 2))
            ok = (cam.depth(X) > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
            ok &= rng.random(len(X)) >= drop
            blobs, members = _merged(uv[ok], merge_px)
            order = rng.permutation(len(blobs))
            ids = np.flatnonzero(ok)
            frame.append(blobs[order])
            frame_labels.append([tuple(int(ids[j]) for j in members[o]) for o in order])
        out.append(frame)
        labels.append(frame_labels)
    return out, labels


def own_observations(labels: list[list[list[tuple[int, ...]]]], dets: list[list[np.ndarray]],
                     markers: int) -> np.ndarray:
    """frames × markers × 2·cameras: each marker's own detections, NaN where it had none or its
    blob merged with another's (a merged blob is no one's position): the perfect association."""
    cams = len(dets[0])
    out = np.full((len(dets), markers, 2 * cams), np.nan)
    for k, (frame, frame_labels) in enumerate(zip(dets, labels, strict=True)):
        for c in range(cams):
            for uv, who in zip(frame[c], frame_labels[c], strict=True):
                if len(who) == 1:
                    out[k, who[0], 2 * c : 2 * c + 2] = uv
    return out


def _merged(uv: np.ndarray, merge_px: float) -> tuple[np.ndarray, list[list[int]]]:
    """Blobs closer than ``merge_px`` as one detection at their mean (greedy, in order), with the
    indices into ``uv`` each blob is made of."""
    left = list(range(len(uv)))
    out, members = [], []
    while left:
        i = left.pop(0)
        close = [j for j in left if np.linalg.norm(uv[j] - uv[i]) < merge_px]
        for j in close:
            left.remove(j)
        out.append(uv[[i, *close]].mean(axis=0))
        members.append([i, *close])
    return np.array(out).reshape(-1, 2), members
