"""The estimate stage: ``out/detections.csv`` + ``calib.yaml`` → ``out/estimates/<method>.csv`` and,
when the clip has truth, ``out/metrics.json`` (schemas in :mod:`pipeline.core.clip`)."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline import consistency
from pipeline.core.camera import StereoRig
from pipeline.core.checks import Check, jump_checks, rig_for_frames, stereo_checks, warn_failed
from pipeline.core.clip import (
    ESTIMATE_COLUMNS,
    TARGET_COLUMNS,
    Clip,
    ClipTruth,
    FootageInfo,
    TargetInfo,
    find_target,
    footage_info,
    load_detections,
)
from pipeline.core.errors import StereotrackError
from pipeline.core.io import write_csv, write_json
from pipeline.core.sync import SyncEstimate, grid_length, resolve_sync
from pipeline.estimators import Estimator, Track, create, registry
from pipeline.estimators import methods as registered_methods
from pipeline.estimators.base import is_builtin, origin
from pipeline.manifest import stereotrack_version
from pipeline.metrics import compute_metrics


@dataclass
class EstimateResult:
    out_dir: Path
    rig: StereoRig
    dt: float
    n_frames: int
    observations: dict[str, np.ndarray]
    tracks: dict[str, dict[str, Track]]  # method → marker → track
    truth: ClipTruth | None
    target: TargetInfo | None = None
    target_tracks: dict[str, Track] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)


def estimate_pixel_sigma(rig: StereoRig, observations: dict[str, np.ndarray]) -> float | None:
    """Detection noise (px) from the data: the DLT leaves one degree of freedom of the four
    stereo coordinates, so the squared reprojection residual of a triangulated point is
    ``σ² χ²(1)``; σ̂² is its mean over all frames and markers. None without stereo frames."""
    from pipeline.core.camera import triangulate

    sq = []
    for Y in observations.values():
        ok = np.all(np.isfinite(Y), axis=1)
        if ok.any():
            X = triangulate(rig, Y[ok])
            good = np.all(np.isfinite(X), axis=1)
            r = rig.project(X[good]) - Y[ok][good]
            sq.append(np.sum(r**2, axis=1))
    if not sq:
        return None
    allsq = np.concatenate(sq)
    # a robust mean: drop the worst 2 % (mislabelled or occluded frames)
    allsq = np.sort(allsq)[: max(1, int(0.98 * len(allsq)))]
    return float(max(np.sqrt(np.mean(allsq)), 0.02))


def estimate_clip(
    clip: str | Path | Clip,
    methods: list[str] | None = None,
    out_dir: str | Path | None = None,
    configs: dict[str, dict] | None = None,
    progress: Callable[[int, int], None] | None = None,
    target_radius: float | None = None,
    calib_units: str | None = None,
    in_dir: str | Path | None = None,
    detections: tuple[dict[str, np.ndarray], FootageInfo] | None = None,
    time_offset: str | float | None = "auto",
    describe: Callable[[str], None] | None = None,
) -> EstimateResult:
    """Run every requested method on every marker of a clip and write estimates and metrics.

    Detections are read from ``in_dir`` (default ``out_dir``, itself default ``CLIP/out``), or
    handed over in memory as ``detections`` (observations per marker and what the detect stage saw
    of the footage) when the stages run together;
    estimates and metrics go to ``out_dir``. Point methods run on each marker; on clips with a
    four-point target the target methods
    (raw measurement, Kalman–Bucy, PnP + KF) run on its four labelled points too. Input checks
    (left/right swapped, epipolar consistency, points behind a camera, track jumps, and the
    detect stage's colour and image-size checks) are warned about and written to
    ``metrics.json`` under ``checks``. ``describe`` is told once what ``progress`` counts.
    """
    clip_ = Clip.open(clip)
    clip = clip_.path
    out_dir = Path(out_dir) if out_dir else clip_.folder / "out"
    in_dir = Path(in_dir) if in_dir else out_dir  # where the detect stage wrote (run: the same folder)
    reg = registry()
    for m in methods or []:
        if m not in reg:
            raise StereotrackError(f"unknown method {m!r} (known: {', '.join(reg)})")
    det_path = in_dir / "detections.csv"
    if detections is None and not det_path.is_file():
        raise StereotrackError("no detections.csv: run `stereotrack detect` first", det_path)
    footage = detections[1] if detections is not None else footage_info(clip, in_dir)
    rig = clip_.rig(calib_units)
    checks = list(footage.checks)
    sized = [c for c in checks if c.name in ("image_size", "calibration_size")]  # the detect stage's verdict
    if footage.frame_size is not None and not sized:
        rig, size_check = rig_for_frames(rig, footage.frame_size, clip)
        checks += [size_check] if size_check else []
        warn_failed([size_check] if size_check else [])
    elif footage.frame_size is not None:
        if any(c.name == "image_size" for c in sized):
            rig = rig.scaled_to(footage.frame_size)  # as the detect stage did
        if detections is None:  # `estimate` on its own says so too (`run`'s detect stage already has)
            warn_failed(sized)
    dt = 1.0 / clip_.fps
    ts = _timestamps(clip_, time_offset)
    grid = grid_length(ts, clip_.fps) if ts is not None else None  # videos that dropped frames are shorter
    truth = clip_.truth(max(footage.frames, grid) if footage.frames is not None and grid is not None else footage.frames)
    obs = detections[0] if detections is not None else load_detections(det_path, footage.frames)
    if not obs:
        raise StereotrackError("no detections in this clip", det_path)
    n = max(max(len(v) for v in obs.values()), grid or 0)
    if truth is not None:
        n = max(n, truth.n_frames)
    obs = {k: np.vstack([v, np.full((n - len(v), 4), np.nan)]) for k, v in obs.items()}
    sync, aligned = resolve_sync(time_offset, rig, obs, clip_.fps, ts)
    new_checks = [_sync_check(sync), *stereo_checks(rig, aligned, clip_.calibration_name),
                  *jump_checks(obs, rig.image_size[0] or 640)]
    warn_failed(new_checks)
    checks += new_checks
    target = find_target(clip_, target_radius, obs)
    methods = methods or registered_methods("point") + (registered_methods("target") if target else [])
    configs = {k: dict(v) for k, v in (configs or {}).items()}
    sigma = estimate_pixel_sigma(rig, aligned)
    if sigma is not None:  # the measurement noise of methods that model it, unless configured
        for m in methods:
            if reg[m].knows_pixel_noise():
                configs.setdefault(m, {}).setdefault("pixel_sigma", sigma)
    tracks: dict[str, dict[str, Track]] = {}
    target_tracks: dict[str, Track] = {}
    resolved: dict[str, dict[str, Any]] = {}
    point_methods = [m for m in methods if reg[m].kind == "point"]
    target_methods = [m for m in methods if reg[m].kind == "target"]
    if target_methods and target is None:
        raise StereotrackError(f"method(s) {', '.join(target_methods)} require a four-point target; this clip has none", clip)
    done, total = 0, len(point_methods) * len(obs) + len(target_methods)
    if describe is not None:
        describe(f"{total} tracks: {len(point_methods)} methods × {len(obs)} markers"
                 + (f" + {len(target_methods)} target methods" if target_methods else ""))
    for m in target_methods:
        assert target is not None
        Yt = np.stack([aligned.get(f"{target.name}_{j}", np.full((n, 4), np.nan)) for j in range(1, 5)], axis=1)
        cfg = {"radius": target.radius, **(target.config if m != "four_point" else {}), **configs.get(m, {})}
        est = create(m, rig, dt, cfg)
        resolved[m] = est.config.model_dump(mode="json")
        target_tracks[m] = _run_method(est, Yt, target.name)
        _write_target_estimates(out_dir / "estimates" / f"{m}.csv", target.name, target_tracks[m], dt)
        done += 1
        if progress is not None:
            progress(done, total)
    for m in point_methods:
        tracks[m] = {}
        modelled = sync.applied and sync.source != "timestamps" and reg[m].models_time_offset
        est = create(m, rig, dt, configs.get(m), time_offset=sync.offset_s if modelled else 0.0)
        resolved[m] = est.config.model_dump(mode="json")
        for marker, Y in (obs if modelled else aligned).items():  # the others see the right camera interpolated
            tracks[m][marker] = _run_method(est, Y, marker)
            done += 1
            if progress is not None:
                progress(done, total)
        _write_estimates(out_dir / "estimates" / f"{m}.csv", tracks[m], dt, truth)
    result = EstimateResult(out_dir, rig, dt, n, obs, tracks, truth, target, target_tracks)
    result.metrics = compute_metrics(result)
    result.metrics["pixel_sigma_estimate"] = sigma
    result.metrics["calibration_units"] = calib_units
    result.metrics["checks"] = [c.as_dict() for c in checks]
    result.metrics["sync"] = sync.as_dict()
    result.metrics["time"] = {"fps": clip_.fps, "dt_s": dt, "source": clip_.fps_source}
    if footage.cameras:
        result.metrics["detection"] = footage.cameras
    result.metrics["stereotrack_version"] = stereotrack_version()
    for m, cfg in resolved.items():
        result.metrics["methods"][m]["config"] = cfg
    write_json(out_dir / "metrics.json", result.metrics)
    return result


def _timestamps(clip: Clip, setting: str | float | None) -> dict[str, np.ndarray] | None:
    """The clip's per-camera frame times (timestamps.csv), unless ``--time-offset`` says otherwise:
    ``off`` ignores them, a number of seconds wins over them (with a warning)."""
    from pipeline.core.clip import TIMESTAMPS

    ts = clip.timestamps if setting != "off" else None
    if ts is not None and isinstance(setting, float):  # the command line wins over the clip's own file
        warnings.warn(f"{clip.folder / TIMESTAMPS}: --time-offset {setting:g} s used instead of this file's frame times",
                      stacklevel=3)
        ts = None
    return ts


def _sync_check(sync: SyncEstimate) -> Check:
    """The offset as an input check: a significant offset found (and corrected) is worth a look."""
    return Check("sync", not (sync.applied and sync.source == "detections"), sync.describe(), sync.offset_s)


def _run_method(est: Estimator, Y: np.ndarray, marker: str) -> Track:
    """``est.run(Y)``; a method that raises (a plugin's bug, say) is one error naming the method,
    where it comes from, the marker and the frame it was on."""
    try:
        return est.run(Y)
    except StereotrackError:
        raise
    except Exception as exc:
        cls = type(est)
        who = "built-in method" if is_builtin(cls) else f"plugin method ({origin(cls)})"
        text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
        raise StereotrackError(f"{who} {est.name!r} raised {type(exc).__name__}: {text} "
                               f"(marker {marker!r}, frame {est.frame})") from None


def _consistency_columns(tr: Track, truth_position: np.ndarray | None) -> np.ndarray:
    """frames × 3: NIS, its degrees of freedom, position NEES (NaN where not defined)."""
    n = len(tr.position)
    out = np.full((n, 3), np.nan)
    if tr.nis is not None and tr.nis_dof is not None:
        out[:, 0], out[:, 1] = tr.nis, np.where(tr.nis_dof > 0, tr.nis_dof, np.nan)
    if truth_position is not None and tr.covariance is not None:
        e = consistency.nees(tr, truth_position)
        out[: len(e), 2] = e
    return out


def _write_estimates(path: Path, tracks: dict[str, Track], dt: float, truth: ClipTruth | None = None) -> None:
    def rows():
        for marker, tr in tracks.items():
            T = truth.positions.get(marker) if truth is not None else None
            cons = _consistency_columns(tr, T)
            for k in range(len(tr.position)):
                yield (k, k * dt, marker, *tr.position[k], *tr.velocity[k], *cons[k], int(tr.predicted[k]))

    write_csv(path, ESTIMATE_COLUMNS, rows())


def _write_target_estimates(path: Path, name: str, tr: Track, dt: float) -> None:
    cons = _consistency_columns(tr, None)

    def rows():
        for k in range(len(tr.position)):
            yield (k, k * dt, name, *tr.position[k], *tr.velocity[k], *cons[k], int(tr.predicted[k]), tr.extra["alpha"][k],
                   tr.extra["distance"][k])

    write_csv(path, TARGET_COLUMNS, rows())


