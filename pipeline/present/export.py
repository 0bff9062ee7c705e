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
    """One method's estimates as an array: frames × markers × 3 (metres, NaN where none)."""

    method: str
    markers: list[str]
    positions: np.ndarray
    fps: float


def read_tracks(out_dir: Path, method: str, fps: float, predicted: bool = False) -> Tracks:
    """``out_dir/estimates/<method>.csv`` as frames × markers × 3 (the columns as
    :func:`pipeline.core.clip.read_positions` reads them); the frames the method only predicted are
    gaps unless ``predicted``."""
    from pipeline.core.clip import positions_from_columns
    from pipeline.core.io import check_frame_column, read_csv

    path = Outputs(out_dir).estimates(method)
    cols = read_csv(path, ["frame", "marker", "x", "y", "z"], numeric=["x", "y", "z"], finite=["frame"])
    check_frame_column(cols["frame"], None, path)
    if not predicted and "predicted" in cols:  # read once: the held frames' positions become gaps
        only = np.asarray(cols["predicted"], dtype=float) == 1
        for a in "xyz":
            cols[a] = np.where(only, np.nan, cols[a])
    pos, n = positions_from_columns(cols)
    markers = list(pos)
    stacked = np.stack([pos[m] for m in markers], axis=1) if markers else np.empty((n, 0, 3))
    return Tracks(method, markers, stacked, fps)


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


def write_c3d(path: Path, t: Tracks) -> None:
    """C3D through ezc3d: POINT:LABELS the marker names, POINT:RATE the frame rate, POINT:UNITS m;
    a missing point is NaN with residual −1."""
    import ezc3d

    c = ezc3d.c3d()
    c["parameters"]["POINT"]["RATE"]["value"] = [float(t.fps)]
    c["parameters"]["POINT"]["LABELS"]["value"] = tuple(t.markers)
    c["parameters"]["POINT"]["UNITS"]["value"] = ["m"]
    pts = np.ones((4, len(t.markers), len(t.positions)))
    pts[:3] = t.positions.transpose(2, 1, 0)
    c["data"]["points"] = pts
    residuals = np.where(np.isfinite(t.positions).all(axis=2).T, 0.0, -1.0)[None]
    c["data"]["meta_points"]["residuals"] = residuals
    with atomic_path(path) as tmp:
        c.write(str(tmp))


def write_wide_csv(path: Path, t: Tracks) -> None:
    """One row per frame: ``frame, t`` and ``<marker>_x, _y, _z`` in metres (``nan`` where none, as
    in every CSV stereotrack writes)."""
    cols = ["frame", "t", *[f"{m}_{a}" for m in t.markers for a in "xyz"]]
    write_csv(path, cols, ((k, k / t.fps, *t.positions[k].ravel()) for k in range(len(t.positions))))


WRITERS = {"trc": write_trc, "c3d": write_c3d, "csv": write_wide_csv}


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
    for m in methods or have:
        path = out_dir / f"{m}.{fmt}"
        path.parent.mkdir(parents=True, exist_ok=True)
        WRITERS[fmt](path, read_tracks(in_dir, m, fps, predicted))
        written.append(path)
    return written
