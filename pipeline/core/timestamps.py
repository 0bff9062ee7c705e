"""``timestamps.csv``: each camera's frame times, read and checked (frame numbers, duplicates, order,
units), every error one line naming the file and line; and the detections placed on the clip's frame
grid by them (offset, jitter and dropped frames at once)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.core.errors import StereotrackError
from pipeline.core.io import read_csv
from pipeline.core.schemas import STEREO, TIMESTAMP_COLUMNS

#: a frame number over this many times a camera's rows (plus 1,000) is a typo, not dropped frames
MAX_FRAME_SPREAD = 100
#: a median frame period this long (s) is a unit mistake (milliseconds), not footage to track in
MAX_PERIOD_S = 5.0


def read_timestamps(path: str | Path, cameras: tuple[str, ...] = STEREO) -> dict[str, np.ndarray]:
    """``timestamps.csv`` → per camera an array of times indexed by frame (NaN where the camera has
    no such frame). Checked, each error naming the file and line: whole non-negative frame numbers
    within reach of the rows, no frame listed twice, times increasing with the frame number, and a
    frame period in seconds (one of milliseconds turns a clip into tens of thousands of frames)."""
    cols = read_csv(path, TIMESTAMP_COLUMNS, finite=["frame", "t"])
    out: dict[str, np.ndarray] = {}
    for cam in cameras:
        rows = np.flatnonzero(cols["camera"] == cam)
        out[cam] = _camera_times(cols["frame"][rows], cols["t"][rows], rows + 2, cam, Path(path))
    if any(not len(v) for v in out.values()):
        raise StereotrackError(f"needs rows for every camera ({', '.join(cameras)})", path)
    t = out[cameras[0]]
    k = np.flatnonzero(np.isfinite(t))
    if len(k) >= 2 and (period := float(np.median(np.diff(t[k]) / np.diff(k)))) >= MAX_PERIOD_S:
        raise StereotrackError(f"the {cameras[0]} camera's frames are {period:g} apart: t must be in seconds "
                               "(milliseconds? divide by 1000)", path)
    return out


def _camera_times(frames: np.ndarray, times: np.ndarray, lines: np.ndarray, cam: str, path: Path) -> np.ndarray:
    """One camera's rows of timestamps.csv → times indexed by frame (NaN where absent), checked."""
    bad = np.flatnonzero((frames < 0) | (frames != np.round(frames)))
    if len(bad):
        raise StereotrackError(f"line {lines[bad[0]]}: frame numbers must be whole and non-negative", path)
    if len(frames) and frames.max() > MAX_FRAME_SPREAD * len(frames) + 1000:
        i = int(np.argmax(frames))
        raise StereotrackError(f"line {lines[i]}: {cam} frame {int(frames[i])} is far beyond the camera's "
                               f"{len(frames)} rows (a typo?)", path)
    order = np.argsort(frames, kind="stable")
    f, tt = frames[order], times[order]
    if len(dup := np.flatnonzero(np.diff(f) == 0)):
        j = order[dup[0] + 1]
        raise StereotrackError(f"line {lines[j]}: {cam} frame {int(frames[j])} is listed twice", path)
    if len(back := np.flatnonzero(np.diff(tt) <= 0)):
        i, j = order[back[0]], order[back[0] + 1]
        raise StereotrackError(f"line {lines[j]}: {cam} frame {int(frames[j])} at {times[j]:g} s is not after frame "
                               f"{int(frames[i])} at {times[i]:g} s: times must increase with the frame number", path)
    t = np.full(int(f[-1]) + 1 if len(f) else 0, np.nan)
    t[f.astype(int)] = tt
    return t


# -- the frame grid, and detections aligned by the times ---------------------------------------


def nominal_frames(t: np.ndarray, fps: float) -> np.ndarray:
    """Each footage frame's place on the clip's frame grid (−1 where the camera has no such frame),
    from the gaps between its frame times: a gap of about m frame periods means m − 1 frames were
    dropped there. Needs no offset between the cameras and tolerates jitter under half a period.
    A frame folder's file numbers come out unchanged; a video that dropped frames is spread out."""
    out = np.full(len(t), -1)
    j = np.flatnonzero(np.isfinite(t))
    if len(j):
        steps = np.maximum(1, np.rint(np.diff(t[j]) * fps)).astype(int)
        out[j] = j[0] + np.concatenate([[0], np.cumsum(steps)])
    return out


def grid_length(ts: dict[str, np.ndarray], fps: float) -> int:
    """Frames on the clip's grid: one past the last nominal frame of either camera."""
    return int(max(nominal_frames(t, fps).max(initial=-1) for t in ts.values())) + 1


def align_by_timestamps(obs: dict[str, np.ndarray], ts: dict[str, np.ndarray], fps: float) -> dict[str, np.ndarray]:
    """Both cameras' detections (each indexed by its own footage: a video that dropped frames is
    shorter) placed on the clip's frame grid (:func:`nominal_frames` of the left camera), the right
    camera's detections interpolated in time to each grid frame's instant (the left frame's time,
    or between its neighbours' where the left camera dropped it). Offset, jitter and dropped
    frames at once; NaN where a camera has nothing."""
    tl, tr = ts["left"], ts["right"]
    g_all = nominal_frames(tl, fps)
    out = {}
    for name, Y in obs.items():
        n = len(Y)
        j = np.flatnonzero((g_all[: n] >= 0) & (g_all[: n] < n))
        g = g_all[j]
        left = np.full((n, 2), np.nan)
        left[g] = Y[j, :2]
        grid = np.interp(np.arange(n), g, tl[j]) if len(g) >= 2 else np.full(n, tl[j[0]] if len(j) else np.nan)
        if len(g) >= 2:  # beyond the left camera's last frame: on at the frame rate
            grid[g[-1] + 1:] = tl[j[-1]] + (np.arange(g[-1] + 1, n) - g[-1]) / fps
        out[name] = np.column_stack([left, right_at_times(Y, tr, grid)])
    return out


def right_at_times(Y: np.ndarray, tr: np.ndarray, at: np.ndarray) -> np.ndarray:
    """The right camera's detections (rows of ``Y`` by its footage index, times ``tr``) at the
    instants ``at``: linear between the frames either side, exact on a frame's own instant."""
    m = min(len(Y), len(tr))
    rf = np.flatnonzero(np.isfinite(tr[:m]) & np.all(np.isfinite(Y[:m, 2:]), axis=1))
    right = np.full((len(at), 2), np.nan)
    order = np.argsort(tr[rf])
    t_r, uv = tr[rf][order], Y[rf, 2:][order]
    if len(t_r) >= 2:
        j = np.searchsorted(t_r, at) - 1
        ok = (j >= 0) & (j + 1 < len(t_r))
        jj = j[ok]
        w = ((at[ok] - t_r[jj]) / (t_r[jj + 1] - t_r[jj]))[:, None]
        right[ok] = (1 - w) * uv[jj] + w * uv[jj + 1]
    exact = np.isin(at, t_r)  # the same instant: no interpolation needed (a 1-frame clip)
    right[exact] = uv[np.searchsorted(t_r, at[exact])]
    return right


def median_offset(ts: dict[str, np.ndarray], fps: float) -> float:
    """The median of right minus left frame time over the grid frames both cameras have."""
    grids = {c: nominal_frames(t, fps) for c, t in ts.items()}
    n = int(max(g.max(initial=-1) for g in grids.values())) + 1
    on = {c: np.full(n, np.nan) for c in ts}
    for c, g in grids.items():
        on[c][g[g >= 0]] = ts[c][g >= 0]
    d = on["right"] - on["left"]
    d = d[np.isfinite(d)]
    return float(np.median(d)) if len(d) else 0.0
