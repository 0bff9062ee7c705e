"""All stages on one clip: (render) → detect → estimate → metrics → report → recording."""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass, replace
from pathlib import Path

from detectors.stage import DetectResult, detect_clip
from pipeline.core.clip import Clip
from pipeline.core.lifeline import OutputLock
from pipeline.core.outputs import Outputs
from pipeline.core.settings import RunHooks, RunSettings
from pipeline.estimate import EstimateResult, estimate_clip
from pipeline.estimators import Track
from pipeline.evaluation.scores import FrameScores
from pipeline.present.recording import Recorder
from pipeline.present.report import write_report
from pipeline.present.report_data import ReportData, report_data

DEFAULT_SCENARIO = "default"


@dataclass
class RunResult:
    clip: Path
    out_dir: Path
    detect: DetectResult
    estimate: EstimateResult
    report: Path
    recording: Path | None
    seconds: float


def process_clip(clip: str | Path, out_dir: str | Path | None = None, settings: RunSettings | None = None,
                 hooks: RunHooks | None = None, lock: bool = True, keep_tracks: bool = True,
                 workers: int = 1) -> RunResult:
    """Detect, estimate, report and record one clip folder into ``out_dir`` (default CLIP/out).

    ``settings`` (:class:`~pipeline.core.settings.RunSettings`) say what is computed: the detector
    and markers (real footage names its markers there; without them the clip's ``markers.yaml``,
    else its ``scenario.yaml``, gives the colours), the methods, the frame rate (winning over
    every rate the clip states, see :attr:`pipeline.core.clip.Clip.fps`), whether the report
    draws figures and whether the recording is written; ``hooks`` hear about stages and progress.
    ``keep_tracks``: whether the result keeps every method's tracks (``estimate.tracks``); either
    way each method's tracks go to the report and the recording as the method finishes, so
    without them a long clip's run holds one method's tracks at a time. ``workers``: processes the
    estimate stage runs its methods in (see :func:`~pipeline.estimate.estimate_clip`), and the
    detect stage its cameras, each encoding its own frames for the recording (see
    :func:`~detectors.stage.detect_clip`).

    With ``lock`` the output folder is locked for the run (a second run on it fails at once,
    naming the holder) and temporary files left there by a killed run are removed first."""
    settings, hooks = settings or RunSettings(), hooks or RunHooks()
    out_dir = Outputs.of(Clip.open(clip).folder, out_dir).folder
    if not lock:
        return _process_clip(Clip.open(clip, settings.fps), out_dir, settings, hooks, keep_tracks, workers)
    with OutputLock(out_dir, f"stereotrack run {clip}"):
        for stale in list(out_dir.rglob(".*.partial-*")):
            stale.unlink(missing_ok=True) if stale.is_file() else shutil.rmtree(stale, ignore_errors=True)
        return _process_clip(Clip.open(clip, settings.fps), out_dir, settings, hooks, keep_tracks, workers)


def run_description(clip: Path, detector: str, metrics: dict) -> str:
    """What a run was, in Markdown, for the recording's text panel: the clip, frames and rate,
    detector, methods, the time offset and the checks that failed."""
    t = metrics.get("time", {})
    failed = [c["message"] for c in metrics.get("checks", []) if not c.get("ok", True)]
    lines = [f"# {clip.name}", "", f"- clip: `{clip}`", f"- frames: {metrics.get('frames', '?')} at {t.get('fps', 0):g} fps "
             f"(from {t.get('source', '?')})", f"- detector: {detector}",
             f"- methods: {', '.join(metrics.get('methods', {}))}"]
    sync = metrics.get("sync") or {}
    if sync.get("source") == "cameras":
        lines.append("- time offsets: not estimated for more than two cameras")
    elif sync:
        lines.append(f"- time offset: {1000 * sync.get('offset_s', 0.0):+.2f} ms, "
                     f"{'applied' if sync.get('applied') else 'not applied'} ({sync.get('source', '?')})")
    lines += ["", "## Checks", "", *([f"- {m}" for m in failed] or ["- all input checks passed"])]
    return "\n".join(lines) + "\n"


def _reference_videos(recorder: Recorder, clip: Clip) -> None:
    """Each camera whose footage is an H.264 video the recording references instead of copying its
    frames; only where frame k of the run is the video's k-th frame (no ``timestamps.csv`` pairing
    frames by time)."""
    from pipeline.core.frames import VIDEO_EXTS, find_camera_source

    if clip.timestamps is not None:
        return
    for cam in clip.cameras:
        src = find_camera_source(clip.folder, cam)
        if src.suffix.lower() in VIDEO_EXTS:
            recorder.reference_video(cam, src)


def _process_clip(clip_: Clip, out_dir: Path, settings: RunSettings, hooks: RunHooks, keep_tracks: bool,
                  workers: int) -> RunResult:
    t0 = time.perf_counter()
    clip = clip_.path  # the clip is read once, handed to every stage
    dt, recorder = 1.0 / clip_.fps, None
    try:  # the recorder is made inside: an interrupt as it opens its file leaves no partial recording
        if settings.recording:
            recorder = Recorder(Outputs(out_dir).recording, dt, name=f"{clip.name} · stereotrack run",
                                cameras=clip_.cameras, app=f"stereotrack: {clip.name}")
        if recorder is not None and settings.images:
            _reference_videos(recorder, clip_)
        hooks.say("detect (frame pairs)")
        framed = replace(hooks, frame=None, image=None)
        if recorder is not None and settings.images:  # each camera's worker makes its frames' JPEGs
            framed = replace(hooks, frame=recorder.log_encoded, image=recorder.encode)
        det = detect_clip(clip_, settings, out_dir, framed, workers=workers)
        hooks.say("estimate")
        data = ReportData(clip_.folder.name, out_dir, {})

        def finished(est: EstimateResult, m: str, tracks: dict[str, Track], scores: dict[str, FrameScores]) -> None:
            data.add_method(est, m, tracks, scores)
            if recorder is not None:
                recorder.method(est, m, tracks, scores)

        est = estimate_clip(clip_, settings, out_dir, replace(hooks, method=finished), detections=det.detections(),
                            keep_tracks=keep_tracks, workers=workers)
        hooks.say("report (figures)" if settings.figures else "report")
        report = write_report(clip_, out_dir, progress=hooks.progress, figures=settings.figures,
                              data=report_data(clip_, est, det.marker_colours, out_dir, data))
        rrd = None
        if recorder is not None:
            hooks.say("recording")
            rrd = recorder.finish(est, det.marker_colours, hooks.progress,
                                  run_description(clip, settings.detector, est.metrics))
    except BaseException:
        if recorder is not None:
            recorder.abort()
        raise
    return RunResult(clip, out_dir, det, est, report, rrd, time.perf_counter() - t0)
