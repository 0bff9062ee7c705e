"""``stereotrack export``: the estimated 3-D tracks of a clip for the tools of motion capture and
biomechanics — OpenSim's TRC (tab-separated text with a marker header), C3D (through ezc3d, the
maintained open C3D library) and a wide CSV — with the marker names, the frame rate and the units
(metres). Frames a method never estimated (before its start), and by default those it only
predicted (held, coasted or gated: ``predicted`` in its estimates), are gaps: ``NaN`` in TRC (an
empty last cell is dropped by OpenSim's own reader, which then finds the row a value short), ``nan``
in CSV, NaN in C3D with the point's residual set to −1 (C3D's "invalid" mark)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.core.errors import StereotrackError
from pipeline.core.io import atomic_path, check_replaceable, write_csv
from pipeline.core.outputs import EXPORT_MARK, OURS, Outputs

FORMATS = ("trc", "c3d", "csv")


@dataclass
class Tracks:
    """One method's estimates as an array: frames × markers × 3 (metres, NaN where none), the
    frames it only predicted (frames × markers), and for C3D each measured point's residual (m) and
    the cameras that saw it (bit c: camera c), where the clip's detections say."""

    method: str
    markers: list[str]
    positions: np.ndarray
    fps: float
    predicted: np.ndarray | None = None
    residuals: np.ndarray | None = None
    camera_masks: np.ndarray | None = None


def read_tracks(out_dir: Path, method: str, fps: float, predicted: bool = False) -> Tracks:
    """``out_dir/estimates/<method>.csv`` as frames × markers × 3 (the columns as
    :func:`pipeline.core.clip.read_positions` reads them); the frames the method only predicted are
    gaps unless ``predicted``."""
    from pipeline.core.clip import positions_from_columns
    from pipeline.core.io import check_frame_column, read_csv

    path = Outputs(out_dir).estimates(method)
    cols = read_csv(path, ["frame", "marker", "x", "y", "z"], numeric=["x", "y", "z"], finite=["frame"])
    check_frame_column(cols["frame"], None, path)
    pos, n = positions_from_columns(cols)
    markers = list(pos)
    stacked = np.stack([pos[m] for m in markers], axis=1) if markers else np.empty((n, 0, 3))
    held = np.zeros((n, len(markers)), dtype=bool)
    if "predicted" in cols:
        only = np.asarray(cols["predicted"], dtype=float) == 1
        column = {m: j for j, m in enumerate(markers)}
        for k, name in zip(cols["frame"][only].astype(int), cols["marker"][only], strict=True):
            held[k, column[str(name)]] = True
    if not predicted:  # the held frames' positions become gaps
        stacked[held] = np.nan
    return Tracks(method, markers, stacked, fps, held)


def clip_fps(out_dir: Path) -> float:
    """The frame rate the estimates were made at (metrics.json's ``time``), else 30."""
    path = Outputs(out_dir).metrics
    try:
        return float(json.loads(path.read_text())["time"]["fps"])
    except (OSError, ValueError, KeyError, TypeError):
        return 30.0


def write_trc(path: Path, t: Tracks) -> None:
    """OpenSim's TRC (PathFileType 4): a header naming the rate, frames, markers and units, then one
    row per frame (``Frame#`` from 1, ``Time`` in s, X/Y/Z per marker; gaps are ``NaN``, which
    OpenSim's reader parses, where its tokenizer drops a row's empty last cells)."""
    n, m = t.positions.shape[:2]
    head = [
        f"PathFileType\t4\t(X/Y/Z)\t{path.name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\tOrigDataStartFrame\tOrigNumFrames",
        f"{t.fps:g}\t{t.fps:g}\t{n}\t{m}\tm\t{t.fps:g}\t1\t{n}",
        "Frame#\tTime\t" + "\t\t\t".join(t.markers) + "\t\t",
        "\t\t" + "\t".join(f"X{i}\tY{i}\tZ{i}" for i in range(1, m + 1)),
    ]
    with atomic_path(path) as tmp, open(tmp, "w", newline="\n") as f:
        f.write("\n".join(head) + "\n\n")
        for k in range(n):
            cells = ["NaN" if not np.isfinite(v) else repr(float(v)) for v in t.positions[k].ravel()]
            f.write(f"{k + 1}\t{k / t.fps:.6f}\t" + "\t".join(cells) + "\n")


#: C3D stores a point's residual as a byte of POINT:SCALE units: 0.1 mm, so residuals up to 25.5 mm
RESIDUAL_UNIT_M = 1e-4


def write_c3d(path: Path, t: Tracks) -> None:
    """C3D through ezc3d: POINT:LABELS the marker names, POINT:RATE the frame rate, POINT:UNITS m.
    Each point's residual follows the format's convention: −1 where there is none (NaN), 0 where
    it was computed rather than measured (a frame the method only predicted, with ``--predicted``),
    and for a measured point the mean distance to the rays of the cameras that saw it (set bits of
    its camera mask), in units of 0.1 mm (POINT:SCALE −0.0001), at least one unit and at most 255."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(t.fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(t.markers)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    c["parameters"]["POINT"]["SCALE"]["value"] = [-RESIDUAL_UNIT_M]
    pts = np.ones((4, len(t.markers), len(t.positions)))
    pts[:3] = t.positions.transpose(2, 1, 0)
    c["data"]["points"] = pts
    have = np.isfinite(t.positions).all(axis=2)
    measured = have & ~(t.predicted if t.predicted is not None else np.zeros_like(have))
    res = np.full(have.shape, RESIDUAL_UNIT_M)  # measured, residual unknown: the smallest positive value
    if t.residuals is not None:
        res = np.where(np.isfinite(t.residuals), np.clip(t.residuals, RESIDUAL_UNIT_M, 255 * RESIDUAL_UNIT_M), res)
    c["data"]["meta_points"]["residuals"] = np.where(measured, res, np.where(have, 0.0, -1.0)).T[None]
    if t.camera_masks is not None:
        bits = (t.camera_masks[..., None] >> np.arange(7)) & 1  # frames × markers × 7 (C3D keeps 7 cameras)
        c["data"]["meta_points"]["camera_masks"] = (bits.astype(bool) & measured[..., None]).transpose(2, 1, 0)
    with atomic_path(path) as tmp:
        c.write(str(tmp))


def write_wide_csv(path: Path, t: Tracks) -> None:
    """One row per frame: ``frame, t`` and ``<marker>_x, _y, _z`` in metres (``nan`` where none, as
    in every CSV stereotrack writes)."""
    cols = ["frame", "t", *[f"{m}_{a}" for m in t.markers for a in "xyz"]]
    write_csv(path, cols, ((k, k / t.fps, *t.positions[k].ravel()) for k in range(len(t.positions))))


WRITERS = {"trc": write_trc, "c3d": write_c3d, "csv": write_wide_csv}
#: a group track's detection in a camera: the group's blob nearest the point's image, within this (px)
GROUP_MATCH_PX = 5.0


def add_ray_residuals(t: Tracks, seen) -> None:
    """Each point's residual (the mean of its distances to the rays through the detections the
    estimate read, :func:`pipeline.core.rig.ray_distances`) and camera mask, from ``seen`` (what
    :func:`pipeline.estimate.observe` makes of the clip). A track of identical markers takes, in
    each camera, the group's blob nearest its image within :data:`GROUP_MATCH_PX`."""
    from pipeline.core.rig import ray_distances

    n, m = t.positions.shape[:2]
    t.residuals, t.camera_masks = np.full((n, m), np.nan), np.zeros((n, m), dtype=np.int64)
    for j, name in enumerate(t.markers):
        Y = _observations(seen, name, t.positions[:, j])
        if Y is None:
            continue
        k = min(n, len(Y))
        d = ray_distances(seen.rig, t.positions[:k, j], Y[:k])
        seen_by = np.isfinite(d)
        count = seen_by.sum(axis=1)
        t.residuals[:k, j] = np.where(count > 0, np.where(seen_by, d, 0.0).sum(axis=1) / np.maximum(count, 1), np.nan)
        t.camera_masks[:k, j] = (seen_by * (1 << np.arange(seen_by.shape[1]))).sum(axis=1)


def _observations(seen, name: str, X: np.ndarray) -> np.ndarray | None:
    """The detections a track of ``name`` was estimated from (frames × 2N), or None if unknown."""
    if name in seen.aligned:
        return seen.aligned[name]
    group = name.split("#", 1)[0]
    if "#" not in name or group not in seen.groups:
        return None
    Y = np.full((len(X), 2 * seen.rig.n), np.nan)
    for k, frame in enumerate(seen.groups[group][: len(X)]):
        if not np.isfinite(X[k]).all():
            continue
        for c, dets in enumerate(frame):
            if len(dets):
                d = np.linalg.norm(dets - seen.rig.cameras[c].project(X[k][None])[0], axis=1)
                if d.min() < GROUP_MATCH_PX:
                    Y[k, 2 * c : 2 * c + 2] = dets[int(np.argmin(d))]
    return Y


def _seen(clip: Path, in_dir: Path):
    """The clip's detections and rig as ``estimate`` read them (its input checks not repeated on
    screen), or None when they cannot be read (residuals are then left unknown)."""
    import warnings

    from pipeline.core.clip import Clip
    from pipeline.core.settings import RunSettings
    from pipeline.estimate import observe

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return observe(Clip.open(clip), in_dir, None, RunSettings())
    except StereotrackError as exc:
        warnings.warn(f"C3D residuals and camera masks left unknown (measured points get the smallest residual): "
                      f"{exc}", stacklevel=3)
        return None


def _current(in_dir: Path, have: list[str], asked: list[str]) -> list[str]:
    """The methods of the last estimate (``metrics.json``'s), of those with estimates: a table an
    earlier estimate left, which the reports no longer draw, is not exported as if it were current
    (named with ``--methods`` it is an error saying so)."""
    try:
        last = list(json.loads(Outputs(in_dir).metrics.read_text()).get("methods") or {})
    except (OSError, ValueError, AttributeError):
        return have
    for m in asked:
        if m not in last:
            raise StereotrackError(f"the estimates of {m!r} are from an earlier estimate: the last one (metrics.json) "
                                   f"ran {', '.join(last)}; run `stereotrack estimate --methods {m}` again", in_dir)
    return [m for m in have if m in last] or have


def export_clip(clip: str | Path, fmt: str, methods: list[str] | None = None, out: str | Path | None = None,
                in_dir: str | Path | None = None, predicted: bool = False) -> list[Path]:
    """Write each method's tracks (default: every method with estimates) as ``<out>/<method>.<fmt>``
    (default ``CLIP/out/export``), the frames it only predicted as gaps unless ``predicted``; the
    paths written."""
    if fmt not in FORMATS:
        raise StereotrackError(f"unknown export format {fmt!r} (known: {', '.join(FORMATS)})")
    in_dir = Outputs.of(clip, in_dir).folder
    est = Outputs(in_dir).estimates_dir
    have = sorted(p.stem for p in est.glob("*.csv")) if est.is_dir() else []
    if not have:
        raise StereotrackError("no estimates here: run `stereotrack estimate` (or `run`) first", est)
    for m in methods or []:
        if m not in have:
            raise StereotrackError(f"no estimates of method {m!r} (have: {', '.join(have)})", est)
    have = _current(in_dir, have, methods or [])
    out_dir = Path(out) if out else Outputs(in_dir).export_dir
    if out:  # a folder the user named: never one of theirs (CLIP/out/export is stereotrack's own)
        check_replaceable(out_dir, OURS, "export")
    fps = clip_fps(in_dir)
    written = []
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / EXPORT_MARK).touch()
    seen = _seen(Path(clip), in_dir) if fmt == "c3d" else None
    for m in methods or have:
        path = out_dir / f"{m}.{fmt}"
        path.parent.mkdir(parents=True, exist_ok=True)
        tracks = read_tracks(in_dir, m, fps, predicted)
        if seen is not None:
            add_ray_residuals(tracks, seen)
        WRITERS[fmt](path, tracks)
        written.append(path)
    return written
