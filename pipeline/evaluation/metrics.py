"""Metrics against the truth and between methods: pure functions of tracks and truth arrays, shared by
``metrics.json``, the report's figures and the recording's series (nothing here reads or writes
files)."""

from __future__ import annotations

from typing import Any, Protocol

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.clip import ClipTruth, TargetInfo
from pipeline.core.rig import Rig
from pipeline.estimators.base import Track
from pipeline.evaluation import consistency
from pipeline.evaluation.scores import FrameScores, errors_per_frame, score_tracks


class Estimates(Protocol):
    """What the metrics need of a run's estimates (the estimate stage's result has it)."""

    n_frames: int
    dt: float
    rig: StereoRig | Rig
    aligned: dict[str, np.ndarray]  # the observations, every camera at the first camera's instants
    tracks: dict[str, dict[str, Track]]
    truth: ClipTruth | None
    target: TargetInfo | None
    target_tracks: dict[str, Track]


def error_stats(est: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """RMSE, mean, median and final 3-D error (m) over frames where both are finite."""
    return stats_of_errors(errors_per_frame(est, truth))


def stats_of_errors(e: np.ndarray) -> dict[str, float]:
    """RMSE, mean, median and final of per-frame 3-D errors (m) over the finite ones."""
    ok = np.isfinite(e)
    if not ok.any():
        return {"rmse": float("nan"), "mean": float("nan"), "median": float("nan"), "final": float("nan"), "frames": 0}
    e = e[ok]
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mean": float(e.mean()), "median": float(np.median(e)),
            "final": float(e[-1]), "frames": int(ok.sum())}


def rmse(a: np.ndarray, b: np.ndarray) -> float | None:
    """RMSE over frames where both are finite (None when there are none)."""
    d = np.asarray(a, float)[: len(b)] - np.asarray(b, float)[: len(a)]
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d**2))) if d.size else None



#: a method whose error is over this many times the run's median is a runaway (clipped, named)
RUNAWAY = 10.0


def ranking(metrics: dict) -> list[str]:
    """Point methods best first: by 3-D RMSE, or by reprojection RMSE without truth (methods with
    neither last, in registry order)."""
    key = "rmse" if metrics.get("has_truth") else "reprojection_rmse_px"
    vals = {m: e.get(key) for m, e in metrics.get("methods", {}).items() if not e.get("target")}
    score = {m: float(v) if isinstance(v, (int, float)) and np.isfinite(v) else np.inf for m, v in vals.items()}
    return sorted(score, key=lambda m: score[m])


def runaways(metrics: dict) -> list[str]:
    """Point methods whose 3-D RMSE (reprojection RMSE without truth) is over :data:`RUNAWAY` ×
    the median of the run's point methods (needs three methods to judge)."""
    key = "rmse" if metrics.get("has_truth") else "reprojection_rmse_px"
    vals = {m: e.get(key) for m, e in metrics.get("methods", {}).items() if not e.get("target")}
    vals = {m: v for m, v in vals.items() if isinstance(v, (int, float)) and np.isfinite(v)}
    if len(vals) < 3:
        return []
    med = float(np.median(list(vals.values())))
    return [m for m, v in vals.items() if v > RUNAWAY * med]


def _note_too_short(entry: dict[str, Any], method: str, n_frames: int) -> None:
    """A method that needs more frames than the clip has: say so (``note``), not an error."""
    from pipeline.estimators import registry

    need = getattr(registry().get(method), "min_frames", 1)
    if n_frames < need:
        entry["note"] = f"needs at least {need} frames; this clip has {n_frames}: no estimate"


def compute_metrics(res: Estimates, point: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """Per method: error statistics against truth (all markers pooled, and per marker),
    reprojection RMSE (px), time per step, and for filters the consistency of their covariance
    (NEES on position against truth, NIS of their innovations; :mod:`pipeline.evaluation.consistency`).
    ``point``: the point methods' entries already computed by :func:`method_metrics` as each
    method finished (a run that does not keep every track); default: from ``res.tracks``."""
    out: dict[str, Any] = {"frames": res.n_frames, "dt": res.dt, "has_truth": res.truth is not None, "methods": {}}
    entries = point if point is not None else {m: method_metrics(res, m, per) for m, per in res.tracks.items()}
    out["methods"].update(entries)
    for m, t in res.target_tracks.items():
        entry = {"target": True, "seconds_per_step": t.seconds_per_step,
                 "steps_per_second": 1.0 / t.seconds_per_step if t.seconds_per_step > 0 else None,
                 "valid_frames": int(np.isfinite(t.extra["alpha"]).sum())}
        if "gated" in t.extra:  # measurements the target filter's gate rejected
            entry["gated"] = int(np.nansum(t.extra["gated"]))
        tg = res.target
        if tg is not None and tg.alpha is not None and tg.distance is not None:
            entry["alpha_rmse_rad"] = rmse(t.extra["alpha"], tg.alpha)
            entry["distance_rmse_m"] = rmse(t.extra["distance"], tg.distance)
        out["methods"][m] = entry
    return out


def method_metrics(res: Estimates, m: str, per_marker: dict[str, Track],
                   scores: dict[str, FrameScores] | None = None) -> dict[str, Any]:
    """One point method's entry of :func:`compute_metrics` from its tracks (marker → track) and
    their per-frame scores (computed here when not given)."""
    if scores is None:
        scores = score_tracks(per_marker, res.truth.positions if res.truth is not None else None)
    entry: dict[str, Any] = {}
    reps = np.concatenate([t.reprojection_error for t in per_marker.values()])
    positions = np.vstack([t.position for t in per_marker.values()])
    fin = np.all(np.isfinite(positions), axis=1)
    behind = res.rig.depths(positions[fin]) <= 0  # N cameras face every way: behind all of them is wrong
    entry["behind_camera"] = int((np.any(behind, axis=1) if isinstance(res.rig, StereoRig) else np.all(behind, axis=1)).sum())
    entry["reprojection_rmse_px"] = float(np.sqrt(np.nanmean(reps**2))) if np.isfinite(reps).any() else None
    nis = [(t.nis, t.nis_dof) for t in per_marker.values() if t.nis is not None]
    if nis:
        entry["nis"] = consistency.summary(np.concatenate([a for a, _ in nis]), np.concatenate([d for _, d in nis]))
    for key, name in (("gated", "gated"), ("restart", "restarts")):
        counts = [np.nansum(t.extra[key]) for t in per_marker.values() if key in t.extra]
        if counts:  # observations the outlier gate rejected (per camera), tracks restarted
            entry[name] = int(sum(counts))
    dropped = {k.split(":", 1)[1]: int(sum(np.nansum(t.extra[k]) for t in per_marker.values() if k in t.extra))
               for k in dict.fromkeys(k for t in per_marker.values() for k in t.extra if k.startswith("dropped:"))}
    if dropped:  # N cameras: which camera's observations the robust triangulation left out, how often
        entry["dropped_cameras"] = dropped
    if isinstance(res.rig, Rig):
        entry["reprojection_per_camera_px"] = _per_camera_reprojection(res, per_marker)
    sps = [t.seconds_per_step for t in per_marker.values()]
    entry["seconds_per_step"] = float(np.mean(sps))
    entry["steps_per_second"] = float(1.0 / np.mean(sps)) if np.mean(sps) > 0 else None
    if res.truth is not None:
        entry.update(_against_truth(scores))
    _note_too_short(entry, m, res.n_frames)
    return entry


def _per_camera_reprojection(res: Estimates, per_marker: dict[str, Track]) -> dict[str, float | None]:
    """N cameras: each camera's RMS pixel distance (per coordinate) between the estimates and its
    own detections at the first camera's instants (single markers; a camera whose RMS stands out
    is mis-calibrated, out of sync or sees a wrong blob)."""
    out: dict[str, float | None] = {}
    for c, name in enumerate(res.rig.names):
        sq = []
        for marker, t in per_marker.items():
            Y = res.aligned.get(marker)
            if Y is None:
                continue
            n = min(len(Y), len(t.position))
            with np.errstate(invalid="ignore"):
                r = res.rig.cameras[c].project(np.nan_to_num(t.position[:n])) - Y[:n, 2 * c : 2 * c + 2]
            ok = np.all(np.isfinite(t.position[:n]), axis=1) & np.all(np.isfinite(r), axis=1)
            sq.append(np.sum(r[ok] ** 2, axis=1))
        allsq = np.concatenate(sq) if sq else np.zeros(0)
        out[name] = float(np.sqrt(np.mean(allsq) / 2)) if len(allsq) else None
    return out


def _against_truth(scores: dict[str, FrameScores]) -> dict[str, Any]:
    """A method's errors against the truth, pooled and per marker, and its position NEES."""
    entry: dict[str, Any] = {}
    errors = {mk: s.error for mk, s in scores.items() if s.error is not None}
    nees = [s.nees for s in scores.values() if s.error is not None and s.nees is not None]
    if errors:
        entry.update(stats_of_errors(np.concatenate(list(errors.values()))))
        markers = {mk: stats_of_errors(e) for mk, e in errors.items()}
        finals = [v["final"] for v in markers.values() if np.isfinite(v["final"])]
        entry["final"] = float(np.mean(finals)) if finals else float("nan")
        entry["markers"] = markers
    if nees:
        entry["nees_position"] = consistency.summary(np.concatenate(nees), 3)
    return entry
