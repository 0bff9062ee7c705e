"""The estimate stage: ``out/detections.csv`` + ``calib.yaml`` → ``out/estimates/<method>.csv`` and,
when the clip has truth, ``out/metrics.json`` (schemas in :mod:`pipeline.core.clip`)."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.checks import Check, calibration_checks, jump_checks, rig_for_frames, stereo_checks, warn_failed
from pipeline.core.clip import (
    DETECTION_COLUMNS,
    ESTIMATE_COLUMNS,
    TARGET_COLUMNS,
    Clip,
    ClipTruth,
    FootageInfo,
    TargetInfo,
    find_target,
    footage_info,
)
from pipeline.core.detections import Detections, GroupDetections, GroupFlags, split_groups
from pipeline.core.errors import StereotrackError, first_line
from pipeline.core.forked import forked_map
from pipeline.core.io import read_csv, write_csv_columns, write_json
from pipeline.core.outputs import Outputs
from pipeline.core.rig import Rig
from pipeline.core.settings import RunHooks, RunSettings
from pipeline.core.sync import SyncEstimate, describe_views, resolve_sync, resolve_view_sync
from pipeline.core.timestamps import grid_length
from pipeline.core.version import stereotrack_version
from pipeline.estimators import Estimator, Track, create, registry
from pipeline.estimators.association import Association, associate, filter_tracks
from pipeline.estimators.kalman_common import RTSMixin, filter_passes_shared
from pipeline.estimators.registration import default_methods, is_builtin, origin
from pipeline.evaluation.identity import MATCH_M, identity_metrics, matched_truth
from pipeline.evaluation.metrics import compute_metrics, method_metrics
from pipeline.evaluation.noise import estimate_pixel_sigma
from pipeline.evaluation.scores import FrameScores, score_track, score_tracks


@dataclass
class EstimateResult:
    out_dir: Path
    rig: StereoRig | Rig
    dt: float
    n_frames: int
    observations: dict[str, np.ndarray]
    #: method → marker → track; a track keeps its covariance's position block (frames × 3 × 3), all
    #: that metrics, report and recording use (the full state covariance of a run's tracks grew
    #: the memory of long clips by a quarter); empty when the run did not keep them
    #: (``keep_tracks=False``: `stereotrack run` and batches, which stream each method's tracks)
    tracks: dict[str, dict[str, Track]]
    truth: ClipTruth | None
    target: TargetInfo | None = None
    target_tracks: dict[str, Track] = field(default_factory=dict)
    metrics: dict[str, Any] = field(default_factory=dict)
    #: method → marker → the track's per-frame scores (kept with the tracks)
    scores: dict[str, dict[str, FrameScores]] = field(default_factory=dict)
    #: the observations with every camera at the first camera's instants (the clip's sync applied)
    aligned: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def truth_positions(self) -> dict[str, np.ndarray] | None:
        """Marker → true positions (frames × 3), or None for real footage."""
        return self.truth.positions if self.truth is not None else None


#: what :func:`estimate_clip` hands each point method's tracks to as the method finishes
MethodSink = Callable[[EstimateResult, str, dict[str, Track], dict[str, FrameScores]], None]


@dataclass
class Observed:
    """What the estimators are given: the rig (as the frames need it), the frame step and count,
    each marker's observations (as detected, and with the right camera aligned to the left's
    times), the time offset, truth, the target, the pixel noise estimated and the input checks."""

    rig: StereoRig | Rig
    dt: float
    n: int
    obs: dict[str, np.ndarray]
    aligned: dict[str, np.ndarray]
    sync: SyncEstimate
    truth: ClipTruth | None
    target: TargetInfo | None
    checks: list[Check]
    footage: FootageInfo
    sigma: float | None
    #: groups of identical markers: per frame, per camera, their detections (no identity)
    groups: dict[str, GroupDetections] = field(default_factory=dict)
    #: each group's association, made once and filtered by every method
    associations: dict[str, Association] = field(default_factory=dict)
    #: a rendered clip's groups → their members' true positions, NaN out of view (:meth:`Clip.group_truth`)
    group_truth: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    #: N cameras: each camera's offset against the first (``sync`` summarises them)
    sync_views: dict[str, SyncEstimate] = field(default_factory=dict)
    #: each group's ``merged`` flags beside its detections (blobs of several images: no one's position)
    merged: dict[str, GroupFlags] = field(default_factory=dict)


def estimate_clip(clip: str | Path | Clip, settings: RunSettings | None = None, out_dir: str | Path | None = None,
                  hooks: RunHooks | None = None, in_dir: str | Path | None = None,
                  detections: Detections | None = None,
                  keep_tracks: bool = True, workers: int = 1) -> EstimateResult:
    """Run every requested method on every marker of a clip and write estimates and metrics.

    Detections are read from ``in_dir`` (default ``out_dir``, itself default ``CLIP/out``), or
    handed over in memory as ``detections`` (observations per marker and what the detect stage saw
    of the footage) when the stages run together; estimates and metrics go to ``out_dir``. Point
    methods run on each marker; on clips with a four-point target the target methods (raw
    measurement, Kalman–Bucy, PnP + KF) run on its four labelled points too. Input checks
    (left/right swapped, epipolar consistency, points behind a camera, track jumps, and the
    detect stage's colour and image-size checks) are warned about and written to
    ``metrics.json`` under ``checks``. ``settings``: the methods, their configs, the calibration's
    units, the time offset, the frame rate. ``hooks.stage`` is told once what ``hooks.progress``
    counts; ``hooks.method`` gets each point method's tracks and scores as the method finishes;
    with ``keep_tracks`` False they are dropped after it, so a long clip's run holds one method's
    tracks at a time, not all of them. ``workers``: processes the methods run in, forked from this
    one (:func:`~pipeline.core.forked.forked_map`; the same numbers as one, which runs them here).
    """
    settings, hooks = settings or RunSettings(), hooks or RunHooks()
    methods = list(settings.methods) if settings.methods else None
    clip_ = Clip.open(clip, settings.fps)
    out_dir = Outputs.of(clip_.folder, out_dir).folder
    reg = registry()
    for m in methods or []:
        if m not in reg:
            raise StereotrackError(f"unknown method {m!r} (known: {', '.join(reg)})")
    seen = observe(clip_, Path(in_dir) if in_dir else out_dir, detections, settings)
    methods, point, target = _split_methods(methods, seen, clip_)
    count = _Count(len(point) * (len(seen.obs) + len(seen.groups)) + len(target), hooks)
    hooks.say(f"estimate ({count.total} tracks: {len(point)} methods × {len(seen.obs) + len(seen.groups)} markers"
                 + (f" + {len(target)} target methods" if target else "") + ")")
    configs = _with_pixel_noise(settings.configs, methods, seen.sigma)
    if point:
        _before_point_methods(seen)
    resolved: dict[str, dict[str, Any]] = {}
    jobs = _jobs([*target, *point], configs)
    runs = _Results(forked_map(partial(_run_job, seen, configs, out_dir), jobs, workers))
    target_tracks = {}
    for m in target:
        target_tracks[m], resolved[m] = runs.take(m)
        count.tick()
    result = EstimateResult(out_dir, seen.rig, seen.dt, seen.n, seen.obs, {}, seen.truth, seen.target, target_tracks,
                            aligned=seen.aligned)
    entries = {}
    for m in point:
        (tracks, scores, identity), resolved[m] = runs.take(m)
        for _ in range(len(seen.aligned) + len(seen.groups)):
            count.tick()
        entries[m] = method_metrics(result, m, tracks, scores)
        if identity:
            entries[m]["identity"] = identity
        if hooks.method is not None:
            hooks.method(result, m, tracks, scores)
        if keep_tracks:
            result.tracks[m], result.scores[m] = tracks, scores
    result.metrics = _metrics(result, seen, clip_, settings.calib_units, resolved, entries)
    write_json(Outputs(out_dir).metrics, result.metrics)
    return result


def _split_methods(asked: list[str] | None, seen: Observed, clip: Clip) -> tuple[list[str], list[str], list[str]]:
    """(the methods to run, the point ones, the target ones): those asked for, else the defaults
    (with N cameras, those that take them); target methods only on a clip with a target."""
    reg = registry()
    methods = asked or default_methods(seen.target is not None)
    if isinstance(seen.rig, Rig) and not asked:  # N cameras: the methods that take them (asked-for others: an error)
        methods = [m for m in methods if reg[m].any_cameras]
    point = [m for m in methods if reg[m].kind == "point"]
    target = [m for m in methods if reg[m].kind == "target"]
    if target and seen.target is None:
        raise StereotrackError(f"method(s) {', '.join(target)} require a four-point target; this clip has none", clip.path)
    return methods, point, target


def _before_point_methods(seen: Observed) -> None:
    """What every point method uses, made once before they run (and fork): each group's
    association, and the rig's triangulation of every frame's observations."""
    _associate_groups(seen)
    if isinstance(seen.rig, StereoRig) and seen.aligned:
        seen.rig.remember(np.concatenate(list(seen.aligned.values())))


class _Count:
    """Tracks done, told to a progress callback."""

    def __init__(self, total: int, hooks: RunHooks) -> None:
        self.done, self.total, self.hooks = 0, total, hooks

    def tick(self) -> None:
        self.done += 1
        self.hooks.tick(self.done, self.total)


def observe(clip: Clip, in_dir: Path, detections: Detections | None, settings: RunSettings) -> Observed:
    """The detections (in memory, else ``in_dir/detections.csv``) padded to the clip's frame grid,
    the rig as the frames need it, the time offset resolved and applied, and the input checks."""
    det_path = Outputs(in_dir).detections
    if detections is None and not det_path.is_file():
        raise StereotrackError("no detections.csv: run `stereotrack detect` first", det_path)
    footage = detections.footage if detections is not None else footage_info(clip.path, in_dir)
    rig, checks = _rig_for_footage(clip, footage, settings.calib_units, warn_sized=detections is None)
    ts = _timestamps(clip, settings.time_offset)
    grid = grid_length(ts, clip.fps) if ts is not None else None  # videos that dropped frames are shorter
    truth_frames = max(footage.frames, grid) if footage.frames is not None and grid is not None else footage.frames
    if truth_frames is not None and isinstance(clip.info.get("frames"), int):  # a rendered clip's own frame count:
        truth_frames = max(truth_frames, clip.info["frames"])  # its last frames may be ones every camera dropped
    truth = clip.truth(truth_frames)
    if detections is None:
        cols = read_csv(det_path, DETECTION_COLUMNS, numeric=["area", "score"], finite=["frame", "u", "v"])
        singles, found, flags = split_groups(cols, footage.frames, det_path, clip.identical_groups(), clip.cameras)
        detections = Detections(singles, footage, found, flags)
    obs, groups = detections.observations, detections.groups
    if not obs and not groups:
        raise StereotrackError("no detections in this clip", det_path)
    lengths = [len(v) for v in obs.values()] + [len(v) for v in groups.values()]
    n = max([*lengths, grid or 0, truth.n_frames if truth is not None else 0])
    width = 2 * len(rig.cameras)
    obs = {k: np.vstack([v, np.full((n - len(v), width), np.nan)]) for k, v in obs.items()}
    groups = {g: [*v, *([[np.zeros((0, 2)) for _ in rig.cameras]] * (n - len(v)))] for g, v in groups.items()}
    merged = {g: [*v, *([[np.zeros(0, dtype=bool) for _ in rig.cameras]] * (n - len(v)))]
              for g, v in detections.merged.items()}
    views: dict[str, SyncEstimate] = {}
    if isinstance(rig, Rig):  # N cameras: each against the first
        views, aligned = resolve_view_sync(settings.time_offset if obs else "off", rig, obs, clip.fps, ts)
        sync = SyncEstimate(0.0, None, any(v.applied for v in views.values()), "cameras", note=describe_views(views))
    else:
        sync, aligned = resolve_sync(settings.time_offset if obs else "off", rig, obs, clip.fps, ts)
    new_checks = [_sync_check(sync), *calibration_checks(rig, clip.calibration_name)]
    if obs and isinstance(rig, StereoRig):  # the pair checks read single markers (groups pair up only when associated)
        new_checks += [*stereo_checks(rig, aligned, clip.calibration_name), *jump_checks(obs, rig.image_size[0] or 640)]
    elif obs:
        new_checks += jump_checks(obs, rig.image_size[0] or 640)
    warn_failed(new_checks)
    return Observed(rig, 1.0 / clip.fps, n, obs, aligned, sync, truth, find_target(clip, settings.target_radius, obs),
                    checks + new_checks, footage, estimate_pixel_sigma(rig, aligned), groups,
                    group_truth=clip.group_truth(truth_frames) if groups else {}, sync_views=views, merged=merged)


def _rig_for_footage(clip: Clip, footage: FootageInfo, calib_units: str | None,
                     warn_sized: bool) -> tuple[StereoRig | Rig, list[Check]]:
    """The calibration as the frames need it (scaled as the detect stage did, or checked against
    the footage's size when it did not say) and the checks so far."""
    rig = clip.rig(calib_units)
    checks = list(footage.checks)
    if isinstance(rig, Rig):  # every camera's size was checked by the detect stage, which has them all
        return rig, checks
    sized = [c for c in checks if c.name in ("image_size", "calibration_size")]  # the detect stage's verdict
    if footage.frame_size is not None and not sized:
        rig, size_check = rig_for_frames(rig, footage.frame_size, clip.path)
        checks += [size_check] if size_check else []
        warn_failed([size_check] if size_check else [])
    elif footage.frame_size is not None:
        if any(c.name == "image_size" for c in sized):
            rig = rig.scaled_to(footage.frame_size)  # as the detect stage did
        if warn_sized:  # `estimate` on its own says so too (`run`'s detect stage already has)
            warn_failed(sized)
    return rig, checks


def _with_pixel_noise(configs: dict[str, dict] | None, methods: list[str], sigma: float | None) -> dict[str, dict]:
    """The methods' settings, with the pixel noise estimated from the data for methods that
    model it and were not told one."""
    out = {k: dict(v) for k, v in (configs or {}).items()}
    reg = registry()
    if sigma is not None:
        for m in methods:
            if reg[m].knows_pixel_noise():
                out.setdefault(m, {}).setdefault("pixel_sigma", sigma)
    return out


def _run_one(seen: Observed, configs: dict[str, dict[str, Any]], out_dir: Path, m: str) -> tuple[Any, dict[str, Any]]:
    """One method on the clip (a target method on the target, a point method on every marker and
    group), its estimates written: (what it found, its settings as resolved)."""
    resolved: dict[str, dict[str, Any]] = {}
    if registry()[m].kind == "target":
        return _run_target(m, seen, configs.get(m, {}), out_dir, resolved), resolved[m]
    return _run_point(m, seen, configs.get(m), out_dir, resolved), resolved[m]


def _jobs(methods: list[str], configs: dict[str, dict[str, Any]]) -> list[tuple[str, ...]]:
    """The methods in jobs for the workers: a smoother with its filter when both have the same
    settings (its backward pass then takes the filter's tracks: one forward pass), and the methods
    that import the same costly module when first run (:attr:`Estimator.startup_imports`) in one
    job, so that one worker pays for it; jobs in the order of their first methods."""
    reg = registry()
    jobs: list[tuple[str, ...]] = []
    job_of: dict[str, int] = {}
    for m in methods:
        cls, filt = reg[m], _smooths(reg[m])
        j = job_of.get(filt) if filt is not None and configs.get(m) == configs.get(filt) else None
        if j is None:
            j = next((job_of[o] for o in job_of if set(reg[o].startup_imports) & set(cls.startup_imports)), None)
        if j is None:
            jobs.append(())
            j = len(jobs) - 1
        jobs[j], job_of[m] = (*jobs[j], m), j
    return jobs


def _smooths(cls: type) -> str | None:
    """The filter a smoother's backward pass takes (None: not a smoother)."""
    return cls.smooths() if issubclass(cls, RTSMixin) else None


def _run_job(seen: Observed, configs: dict[str, dict[str, Any]], out_dir: Path, job: tuple[str, ...]
             ) -> list[tuple[str, tuple[Any, dict[str, Any]]]]:
    """The methods of one job in one process (:func:`_run_one` each), a filter's forward passes shared
    with its smoother."""
    with filter_passes_shared():
        return [(m, _run_one(seen, configs, out_dir, m)) for m in job]


class _Results:
    """The jobs' results, taken method by method in whatever order the caller needs them (those
    that come before theirs are kept until taken)."""

    def __init__(self, jobs: Iterator[list[tuple[str, Any]]]) -> None:
        self.jobs, self.kept = jobs, dict[str, Any]()

    def take(self, m: str) -> Any:
        while m not in self.kept:
            self.kept.update(next(self.jobs))
        return self.kept.pop(m)


def _associate_groups(seen: Observed) -> None:
    """Each group of identical markers associated once, before the methods that filter it run."""
    for group, dets in seen.groups.items():
        if group not in seen.associations:
            seen.associations[group] = associate(list(seen.rig.cameras), seen.dt, dets, merged=seen.merged.get(group))


def _run_target(m: str, seen: Observed, config: dict, out_dir: Path, resolved: dict) -> Track:
    """One target method on the target's four labelled points; writes its estimates."""
    target = seen.target
    assert target is not None
    Yt = np.stack([seen.aligned.get(f"{target.name}_{j}", np.full((seen.n, 4), np.nan)) for j in range(1, 5)], axis=1)
    dynamics = target.config if registry()[m].models_target_dynamics else {}
    est = create(m, seen.rig, seen.dt, {"radius": target.radius, **dynamics, **config})
    resolved[m] = est.config.model_dump(mode="json")
    track = _run_method(est, Yt, target.name)
    _write_target_estimates(Outputs(out_dir).estimates(m), target.name, track, seen.dt)
    return track


def _run_group(m: str, seen: Observed, group: str, config: dict | None
               ) -> tuple[dict[str, Track], dict[str, FrameScores], dict[str, Any] | None]:
    """One point method behind the association of a group of identical markers: its tracks
    (``<group>#<n>``), their scores against the truth marker each follows frame by frame, and the
    identity metrics (None without truth)."""
    tracks = filter_tracks(seen.rig, seen.dt, seen.associations[group], m, group, config)
    truth = seen.group_truth.get(group, {})
    if not truth:
        return tracks, score_tracks(tracks, None), None
    positions = {k: t.position for k, t in tracks.items()}
    follows, markers = matched_truth(truth, positions)
    scores = {k: score_track(t, follows[k]) for k, t in tracks.items()}
    for k, s in scores.items():
        s.follows = markers[k]
    return tracks, scores, identity_metrics(truth, positions, MATCH_M)


def _run_point(m: str, seen: Observed, config: dict | None, out_dir: Path, resolved: dict
               ) -> tuple[dict[str, Track], dict[str, FrameScores], dict[str, dict[str, Any] | None]]:
    """One point method on every marker, and behind the association on each group of identical
    markers; writes its estimates. Every method sees the right camera interpolated to the left
    camera's instants when an offset is applied: the EKF's and UKF's own offset model (the right
    camera at ``p + v·δ``) was worse on every simulated case (1.13–3.02× the synchronised RMSE against
    1.03–1.07× interpolated on a sine path, ½–2 frames late) and metres off at an offset of 1.5 s;
    it stays for callers who hand ``time_offset`` to the estimator."""
    est = create(m, seen.rig, seen.dt, config)
    resolved[m] = est.config.model_dump(mode="json")
    tracks, identity = {}, {}
    for marker, Y in seen.aligned.items():
        tracks[marker] = _run_method(est, Y, marker)
    scores = score_tracks(tracks, seen.truth.positions if seen.truth is not None else None)
    for g in seen.groups:
        mine, mine_scores, identity[g] = _run_group(m, seen, g, config)
        tracks.update(mine)
        scores.update(mine_scores)
    _write_estimates(Outputs(out_dir).estimates(m), tracks, seen.dt, scores)
    for tr in tracks.values():  # what the later stages use of it: memory that does not grow 4× per frame
        if tr.covariance is not None and tr.covariance.shape[1] > 3:
            tr.covariance = np.ascontiguousarray(tr.covariance[:, :3, :3])
    return tracks, scores, identity


def _metrics(result: EstimateResult, seen: Observed, clip: Clip, calib_units: str | None,
             resolved: dict[str, dict[str, Any]], point: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """metrics.json: the metrics of every method, with the run's settings, checks and time."""
    metrics = compute_metrics(result, point)
    metrics.update({"pixel_sigma_estimate": seen.sigma, "calibration_units": calib_units,
                    "checks": [c.as_dict() for c in seen.checks], "sync": seen.sync.as_dict(),
                    **({"sync_cameras": {k: v.as_dict() for k, v in seen.sync_views.items()}} if seen.sync_views else {}),
                    "time": {"fps": clip.fps, "dt_s": seen.dt, "source": clip.fps_source}})
    if seen.footage.cameras:
        metrics["detection"] = seen.footage.cameras
    metrics["stereotrack_version"] = stereotrack_version()
    for m, cfg in resolved.items():
        metrics["methods"][m]["config"] = cfg
    return metrics


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
        text = first_line(exc) if str(exc).strip() else ""
        raise StereotrackError(f"{who} {est.name!r} raised {type(exc).__name__}: {text} "
                               f"(marker {marker!r}, frame {est.frame})") from None


def _write_estimates(path: Path, tracks: dict[str, Track], dt: float, scores: dict[str, FrameScores]) -> None:
    parts = [_track_columns(marker, marker.split("#", 1)[0], tr, dt, scores[marker].columns())
             for marker, tr in tracks.items()]
    write_csv_columns(path, ESTIMATE_COLUMNS, _stacked(parts, len(ESTIMATE_COLUMNS)))


def _write_target_estimates(path: Path, name: str, tr: Track, dt: float) -> None:
    cols = [*_track_columns(name, name, tr, dt, score_track(tr, None).columns()), tr.extra["alpha"], tr.extra["distance"]]
    write_csv_columns(path, TARGET_COLUMNS, cols)


def _track_columns(marker: str, group: str, tr: Track, dt: float, cons: np.ndarray) -> list:
    """One track's rows of the estimates CSV, column by column: frame, t, marker, position,
    velocity, the consistency columns, predicted, group."""
    n = len(tr.position)
    frames = np.arange(n)
    return [frames, frames * dt, [marker] * n, *tr.position.T, *tr.velocity.T, *cons.T,
            np.asarray(tr.predicted, dtype=int), [group] * n]


def _stacked(parts: list[list], width: int) -> list:
    """Tracks' columns one after another (arrays joined, name lists added)."""
    if not parts:
        return [[] for _ in range(width)]
    return [np.concatenate(c) if isinstance(c[0], np.ndarray) else [v for p in c for v in p] for c in zip(*parts, strict=True)]


