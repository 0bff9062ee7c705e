"""``timestamps.csv``: each camera's frame times, read and checked (frame numbers, duplicates, order,
units), every error one line naming the file and line."""

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
