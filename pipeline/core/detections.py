"""The detections the estimate stage takes: ``detections.csv``'s columns (or the detect stage's, in
memory) as each single marker's observations (frames × ``[u1, v1, u2, v2]``) and each group of
identical markers' detections per frame and camera (no identity)."""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.core.clip import DETECTION_COLUMNS, FootageInfo
from pipeline.core.errors import StereotrackError
from pipeline.core.io import check_frame_column, read_csv

#: a group's detections: per frame, per camera, k × 2 pixels (no identity)
GroupDetections = list[list[np.ndarray]]
#: beside a group's detections: per frame, per camera, k flags, True for a blob of merged images
GroupFlags = list[list[np.ndarray]]


@dataclass
class Detections:
    """What the estimate stage takes of the detect stage: each single marker's observations (frames
    × 4), each group of identical markers' detections per frame and camera, and the footage seen."""

    observations: dict[str, np.ndarray]
    footage: FootageInfo
    groups: dict[str, GroupDetections] = field(default_factory=dict)
    #: each group's ``merged`` flags, beside its detections (absent: none known)
    merged: dict[str, GroupFlags] = field(default_factory=dict)


STEREO = ("left", "right")


def _camera_index(cols: dict[str, np.ndarray], cameras: tuple[str, ...], path: str | Path) -> np.ndarray:
    """Each row's camera as its index in ``cameras`` (an unknown name: an error naming the line)."""
    index = {name: c for c, name in enumerate(cameras)}
    cams = np.array([index.get(str(c), -1) for c in cols["camera"]], dtype=int)
    if (cams < 0).any():
        i = int(np.flatnonzero(cams < 0)[0])
        raise StereotrackError(f"line {i + 2}: unknown camera {cols['camera'][i]!r} (expected {'/'.join(cameras)})", path)
    return cams


def split_groups(cols: dict[str, np.ndarray], n_frames: int | None, path: str | Path,
                 groups: Collection[str] = (), cameras: tuple[str, ...] = STEREO
                 ) -> tuple[dict[str, np.ndarray], dict[str, GroupDetections], dict[str, GroupFlags]]:
    """Detection columns → (single markers' observations, as :func:`observations_from_columns`;
    groups' detections; their ``merged`` flags, all False without that column). A name is a group
    when ``groups`` declares it or when it has several rows in one frame and camera (identical
    markers: the detector reports every blob of their colour)."""
    frames = np.asarray(cols["frame"], dtype=float)
    if not len(frames):
        return {}, {}, {}
    check_frame_column(frames, n_frames, path)
    n = max(int(frames.max()) + 1, n_frames or 0)
    cams = _camera_index(cols, cameras, path)
    names = np.asarray(cols["marker"]).astype(str)
    many = group_names(cols, groups, cameras, path)
    single = ~np.isin(names, sorted(many))
    obs = observations_from_columns({k: np.asarray(v)[single] for k, v in cols.items()}, n_frames, path, cameras)
    merged = _merged_column(cols, path)
    out: dict[str, GroupDetections] = {}
    flags: dict[str, GroupFlags] = {}
    for g in sorted(many & set(names.tolist())):
        mine = np.flatnonzero(names == g)
        table: GroupDetections = [[np.zeros((0, 2)) for _ in cameras] for _ in range(n)]
        flag: GroupFlags = [[np.zeros(0, dtype=bool) for _ in cameras] for _ in range(n)]
        for k, c, u, v, m in zip(frames[mine].astype(int), cams[mine], np.asarray(cols["u"])[mine],
                                 np.asarray(cols["v"])[mine], merged[mine], strict=True):
            table[k][c] = np.vstack([table[k][c], [u, v]])
            flag[k][c] = np.append(flag[k][c], m)
        out[g], flags[g] = table, flag
    return obs, out, flags


def group_names(cols: dict[str, np.ndarray], groups: Collection[str] = (), cameras: tuple[str, ...] = STEREO,
                path: str | Path = "detections.csv") -> set[str]:
    """The names that are groups of identical markers: those ``groups`` declares and those with
    several rows in one frame and camera."""
    frames = np.asarray(cols["frame"], dtype=float)
    names = np.asarray(cols["marker"]).astype(str)
    keys = frames.astype(np.int64) * len(cameras) + _camera_index(cols, cameras, path)
    return set(groups) | {str(m) for m in np.unique(names) if len(np.unique(keys[names == m])) < (names == m).sum()}


def _merged_column(cols: dict[str, np.ndarray], path: str | Path) -> np.ndarray:
    """The optional ``merged`` column as booleans (all False without it); anything but 0/1 (or
    empty, read as 0) is an error naming the line."""
    n = len(cols["frame"])
    if "merged" not in cols:
        return np.zeros(n, dtype=bool)
    raw = np.asarray(cols["merged"])
    if raw.dtype == object:
        raw = np.array([0.0 if str(x).strip() == "" else _number(x) for x in raw])
    vals = np.nan_to_num(raw.astype(float), nan=0.0)
    bad = np.flatnonzero((vals != 0) & (vals != 1))
    if len(bad):
        raise StereotrackError(f"line {bad[0] + 2}: merged must be 0 or 1, got {cols['merged'][bad[0]]!r}", path)
    return vals == 1


def _number(x: object) -> float:
    try:
        return float(str(x))
    except ValueError:
        return float("inf")  # not a number: reported by the caller as not 0 or 1


def load_detections(path: str | Path, n_frames: int | None = None, cameras: tuple[str, ...] = STEREO
                    ) -> dict[str, np.ndarray]:
    """``detections.csv`` → per marker an array frames × 4 ``[u1, v1, u2, v2]`` (NaN = missed),
    keeping the highest-scoring detection per frame, camera and marker.

    ``n_frames`` is the clip's frame count: a row outside ``0 .. n_frames − 1`` is an error naming
    the line, as are non-numeric or non-finite fields and unknown cameras.
    """
    path = Path(path)
    cols = read_csv(path, DETECTION_COLUMNS, numeric=["area", "score"], finite=["frame", "u", "v"])
    return observations_from_columns(cols, n_frames, path, cameras)


def observations_from_columns(cols: dict[str, np.ndarray], n_frames: int | None, path: str | Path,
                              cameras: tuple[str, ...] = STEREO) -> dict[str, np.ndarray]:
    """Detection columns (the ``detections.csv`` schema, from the file or from the detect stage
    in memory) → per marker frames × 2N ``[u1, v1, u2, v2, …]`` (N = ``cameras``), best score per
    frame and camera."""
    if len(cols["frame"]) == 0:
        return {}
    frames = np.asarray(cols["frame"], dtype=float)
    check_frame_column(frames, n_frames, path)
    n = max(int(frames.max()) + 1, n_frames or 0)
    out: dict[str, np.ndarray] = {}
    best: dict[tuple[str, int, int], float] = {}
    index = _camera_index(cols, cameras, path)
    for k, c, name, u, v, score in zip(frames.astype(int), index.tolist(), cols["marker"], cols["u"], cols["v"],
                                       cols["score"], strict=True):
        score = score if np.isfinite(score) else 0.0
        arr = out.get(name := str(name))
        if arr is None:  # not setdefault: that would build a frames × 2N array for every row
            arr = out[name] = np.full((n, 2 * len(cameras)), np.nan)
        key = (name, int(k), c)
        if key in best and best[key] >= score:
            continue
        best[key] = score
        arr[k, 2 * c : 2 * c + 2] = (u, v)
    return out


#: a group's blob over this many times the group's median blob area, and less round than
#: :data:`MERGED_ROUNDNESS`, holds merged images (on the rendered ``identical`` clip, 150 frames:
#: 96 % of the blobs so flagged image two or more markers)
MERGED_AREA = 1.4
MERGED_ROUNDNESS = 0.8
#: frames on either side of a blob's whose areas make its group's median (markers change size with depth)
MERGED_SPAN = 15


def blob_flags(cols: dict[str, np.ndarray], groups: Collection[str] = ()) -> tuple[np.ndarray, np.ndarray]:
    """Each detection row's ``index`` (its number among the rows of its marker, frame and camera, in
    order) and ``merged`` flag (a group's blob over :data:`MERGED_AREA` × the group's median area in
    that camera over the frame and :data:`MERGED_SPAN` on either side, and with a roundness (the
    ``score``) under :data:`MERGED_ROUNDNESS`: two or more images merged)."""
    frames = np.asarray(cols["frame"], dtype=np.int64)
    keys = list(zip(frames.tolist(), (str(c) for c in cols["camera"]), (str(m) for m in cols["marker"]), strict=True))
    seen: dict[tuple, int] = {}
    index = np.empty(len(keys), dtype=np.int64)
    for i, key in enumerate(keys):
        index[i] = seen[key] = seen.get(key, -1) + 1
    merged = np.zeros(len(keys), dtype=np.int64)
    area, score = np.asarray(cols["area"], dtype=float), np.asarray(cols["score"], dtype=float)
    names, cams = np.asarray(cols["marker"]).astype(str), np.asarray(cols["camera"]).astype(str)
    for g in groups:
        for cam in np.unique(cams[names == g]):
            rows = np.flatnonzero((names == g) & (cams == cam))
            merged[rows] = _over_median(frames[rows], area[rows], score[rows] < MERGED_ROUNDNESS)
    return index, merged


def _over_median(frames: np.ndarray, area: np.ndarray, candidate: np.ndarray) -> np.ndarray:
    """1 where a ``candidate`` row's ``area`` exceeds :data:`MERGED_AREA` × the median of the areas
    within :data:`MERGED_SPAN` frames (rows sorted or not; the median only for the candidates)."""
    order = np.argsort(frames, kind="stable")
    f, a = frames[order], area[order]
    out = np.zeros(len(f), dtype=np.int64)
    for r in np.flatnonzero(candidate[order]):
        lo = np.searchsorted(f, f[r] - MERGED_SPAN, side="left")
        hi = np.searchsorted(f, f[r] + MERGED_SPAN, side="right")
        out[order[r]] = a[r] > MERGED_AREA * np.median(a[lo:hi])
    return out
