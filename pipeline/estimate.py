"""The estimate stage: ``out/detections.csv`` + ``calib.yaml`` → ``out/estimates/<method>.csv`` and,
when the clip has truth, ``out/metrics.json`` (SPEC §3)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from detectors.stage import load_detections
from pipeline.camera import StereoRig, load_calibration
from pipeline.errors import StereotrackError
from pipeline.estimators import POINT_METHODS, Track, create
from pipeline.io import read_csv, write_csv, write_json

ESTIMATE_COLUMNS = ["frame", "t", "marker", "x", "y", "z", "vx", "vy", "vz"]


@dataclass
class ClipTruth:
    """Per-marker truth positions (frames × 3) and the clip's frame count and fps."""

    positions: dict[str, np.ndarray]
    n_frames: int


@dataclass
class EstimateResult:
    out_dir: Path
    rig: StereoRig
    dt: float
    n_frames: int
    observations: dict[str, np.ndarray]
    tracks: dict[str, dict[str, Track]]  # method → marker → track
    truth: ClipTruth | None
    metrics: dict[str, Any] = field(default_factory=dict)


def clip_fps(clip: Path) -> float:
    """Frame rate from ``scenario.yaml``, else the left video's header, else 30."""
    if (clip / "scenario.yaml").is_file():
        from renderers.scenario import load_scenario

        return load_scenario(clip / "scenario.yaml").fps
    from detectors.frames import CameraReader, find_camera_source

    try:
        fps = CameraReader(find_camera_source(clip, "left")).fps
    except StereotrackError:
        fps = 0.0
    return fps or 30.0


def load_truth(clip: Path) -> ClipTruth | None:
    """``truth.csv`` → per-marker positions, or None for real footage."""
    path = clip / "truth.csv"
    if not path.is_file():
        return None
    cols = read_csv(path, ["frame", "marker", "x", "y", "z"])
    n = int(np.nanmax(cols["frame"])) + 1 if len(cols["frame"]) else 0
    pos: dict[str, np.ndarray] = {}
    for k, name, x, y, z in zip(cols["frame"].astype(int), cols["marker"], cols["x"], cols["y"], cols["z"], strict=True):
        pos.setdefault(str(name), np.full((n, 3), np.nan))[k] = (x, y, z)
    return ClipTruth(pos, n)


def error_stats(est: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """RMSE, mean, median and final 3-D error (m) over frames where both are finite."""
    e = np.linalg.norm(est - truth, axis=1)
    ok = np.isfinite(e)
    if not ok.any():
        return {"rmse": float("nan"), "mean": float("nan"), "median": float("nan"), "final": float("nan"), "frames": 0}
    e = e[ok]
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mean": float(e.mean()), "median": float(np.median(e)),
            "final": float(e[-1]), "frames": int(ok.sum())}


def estimate_clip(
    clip: str | Path,
    methods: list[str] | None = None,
    out_dir: str | Path | None = None,
    configs: dict[str, dict] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> EstimateResult:
    """Run every requested method on every marker of a clip and write estimates and metrics."""
    clip = Path(clip)
    out_dir = Path(out_dir) if out_dir else clip / "out"
    rig = load_calibration(clip)
    dt = 1.0 / clip_fps(clip)
    truth = load_truth(clip)
    det_path = out_dir / "detections.csv"
    if not det_path.is_file():
        raise StereotrackError("no detections.csv: run `stereotrack detect` first", det_path)
    obs = load_detections(det_path, truth.n_frames if truth else None)
    if not obs:
        raise StereotrackError("detections.csv holds no detections", det_path)
    n = max(len(v) for v in obs.values())
    obs = {k: np.vstack([v, np.full((n - len(v), 4), np.nan)]) for k, v in obs.items()}
    methods = methods or list(POINT_METHODS)
    configs = configs or {}
    tracks: dict[str, dict[str, Track]] = {}
    done, total = 0, len(methods) * len(obs)
    for m in methods:
        tracks[m] = {}
        for marker, Y in obs.items():
            tracks[m][marker] = create(m, rig, dt, configs.get(m)).run(Y)
            done += 1
            if progress is not None:
                progress(done, total)
        _write_estimates(out_dir / "estimates" / f"{m}.csv", tracks[m], dt)
    result = EstimateResult(out_dir, rig, dt, n, obs, tracks, truth)
    result.metrics = compute_metrics(result)
    write_json(out_dir / "metrics.json", result.metrics)
    return result


def _write_estimates(path: Path, tracks: dict[str, Track], dt: float) -> None:
    def rows():
        for marker, tr in tracks.items():
            for k in range(len(tr.position)):
                yield (k, k * dt, marker, *tr.position[k], *tr.velocity[k])

    write_csv(path, ESTIMATE_COLUMNS, rows())


def compute_metrics(res: EstimateResult) -> dict[str, Any]:
    """Per method: error statistics against truth (all markers pooled, and per marker),
    reprojection RMSE (px) and time per step."""
    out: dict[str, Any] = {"frames": res.n_frames, "dt": res.dt, "has_truth": res.truth is not None, "methods": {}}
    for m, per_marker in res.tracks.items():
        entry: dict[str, Any] = {}
        reps = np.concatenate([t.reprojection_error for t in per_marker.values()])
        entry["reprojection_rmse_px"] = float(np.sqrt(np.nanmean(reps**2))) if np.isfinite(reps).any() else None
        sps = [t.seconds_per_step for t in per_marker.values()]
        entry["seconds_per_step"] = float(np.mean(sps))
        entry["steps_per_second"] = float(1.0 / np.mean(sps)) if np.mean(sps) > 0 else None
        if res.truth is not None:
            est, tru, markers = [], [], {}
            for marker, t in per_marker.items():
                if marker not in res.truth.positions:
                    continue
                T = res.truth.positions[marker][: len(t.position)]
                P = t.position[: len(T)]
                markers[marker] = error_stats(P, T)
                est.append(P)
                tru.append(T)
            if est:
                entry.update(error_stats(np.vstack(est), np.vstack(tru)))
                entry["final"] = float(np.nanmean([v["final"] for v in markers.values()]))
                entry["markers"] = markers
        out["methods"][m] = entry
    return out
