"""Batch processing of clip folders: a local process pool by default, a Dask cluster when asked.

Each clip is processed into ``OUTPUT/.<name>.partial`` and renamed to ``OUTPUT/<name>`` only when
complete, so a killed batch leaves no half-written clip and a rerun skips finished clips
(``force`` redoes them). One failing clip is recorded with its error and never stops the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import shutil
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from pipeline.camera import has_calibration
from pipeline.errors import StereotrackError
from pipeline.io import ensure_dir, write_csv, write_text

SUMMARY_COLUMNS = ["clip", "status", "method", "rmse_m", "final_m", "reprojection_rmse_px", "steps_per_second", "error"]


@dataclass
class ClipOutcome:
    clip: str
    status: str  # "ok", "failed", "skipped"
    metrics: dict = field(default_factory=dict)
    error: str = ""


def find_clips(input_dir: str | Path) -> list[Path]:
    """Clip folders under ``input_dir``: folders holding a calibration and left/right footage."""
    input_dir = Path(input_dir)
    if not input_dir.is_dir():
        raise StereotrackError("no such input folder", input_dir)
    clips = []
    for d in sorted(p for p in [input_dir, *input_dir.rglob("*")] if p.is_dir()):
        if d.name.startswith(".") or d.name in ("out", "left", "right", "estimates", "figures"):
            continue
        names = {p.name for p in d.iterdir()}
        has_calib = has_calibration(d)
        has_left = any(n.startswith("left") for n in names)
        if has_calib or (has_left and any(n.startswith("right") for n in names)):
            clips.append(d)
    return clips


def _process_one(clip: str, out_root: str, detector: str, methods: list[str] | None, single_thread: bool = False,
                 marker_specs: list[str] | None = None, calib_units: str | None = None) -> ClipOutcome:
    """Worker entry point (runs in a pool process or on a Dask worker). ``single_thread`` keeps
    OpenCV to one thread so that parallel workers do not oversubscribe the cores."""
    import json

    if single_thread:
        import cv2

        cv2.setNumThreads(1)

    from pipeline.run import process_clip

    clip_p, name = Path(clip), Path(clip).name
    final, partial = Path(out_root) / name, Path(out_root) / f".{name}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    try:
        import warnings

        from detectors.stage import resolve_marker_specs

        specs = resolve_marker_specs(clip_p, None, marker_specs)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            process_clip(clip_p, partial, detector=detector, methods=methods, images_in_recording=False,
                         marker_specs=specs, calib_units=calib_units)
        for w in caught:  # the clip's warnings reach the user through the summary
            print(f"warning: {w.message}", flush=True)
        if final.exists():
            shutil.rmtree(final)
        partial.rename(final)
        return ClipOutcome(name, "ok", json.loads((final / "metrics.json").read_text()))
    except StereotrackError as exc:
        shutil.rmtree(partial, ignore_errors=True)
        return ClipOutcome(name, "failed", error=str(exc))
    except Exception as exc:
        shutil.rmtree(partial, ignore_errors=True)
        last = traceback.extract_tb(exc.__traceback__)[-1]
        return ClipOutcome(name, "failed", error=f"{type(exc).__name__}: {exc} ({Path(last.filename).name}:{last.lineno})")


def run_batch(
    input_dir: str | Path,
    output_dir: str | Path,
    workers: int = 2,
    scheduler: str | None = None,
    force: bool = False,
    detector: str = "blob",
    methods: list[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
    marker_specs: list[str] | None = None,
    calib_units: str | None = None,
) -> list[ClipOutcome]:
    """Process every clip under ``input_dir``; write ``summary.csv`` and ``summary.md``.

    ``marker_specs`` (``--markers``) apply to every clip; else a clip's own ``markers.yaml``, else
    ``INPUT/markers.yaml``, else the clip's scenario.yaml gives its markers.

    ``scheduler``: None for a local process pool; ``"local"`` for a Dask ``LocalCluster`` of
    ``workers`` processes; a ``tcp://host:port`` address for an existing Dask scheduler.
    """
    from detectors.stage import MARKERS_FILE, read_markers_file

    clips = find_clips(input_dir)
    if not clips:
        raise StereotrackError("no clip folders here (a clip holds left/right videos or frame folders and a calibration)",
                               input_dir)
    if not marker_specs and (Path(input_dir) / MARKERS_FILE).is_file():
        marker_specs = read_markers_file(Path(input_dir) / MARKERS_FILE)
    out_root = ensure_dir(output_dir)
    for stale in out_root.glob(".*.partial"):
        shutil.rmtree(stale, ignore_errors=True)
    outcomes: dict[str, ClipOutcome] = {}
    todo = []
    for c in clips:
        if not force and (out_root / c.name / "metrics.json").is_file() and (out_root / c.name / "report.md").is_file():
            import json

            outcomes[c.name] = ClipOutcome(c.name, "skipped", json.loads((out_root / c.name / "metrics.json").read_text()))
        else:
            todo.append(c)
    done = len(outcomes)
    if progress is not None:
        progress(done, len(clips))
    args = [(str(c), str(out_root), detector, methods, workers > 1, marker_specs, calib_units) for c in todo]
    if todo and scheduler is None:
        with cf.ProcessPoolExecutor(max_workers=max(1, workers), mp_context=mp.get_context("spawn")) as pool:
            futs = [pool.submit(_process_one, *a) for a in args]
            for f in cf.as_completed(futs):
                o = f.result()
                outcomes[o.clip] = o
                done += 1
                if progress is not None:
                    progress(done, len(clips))
    elif todo:
        import logging

        from dask.distributed import Client, LocalCluster, as_completed

        cluster = LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True,
                               dashboard_address=None, silence_logs=logging.WARNING) if scheduler == "local" else None
        try:
            try:
                # Dask's own setting (DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT) wins; 10 s otherwise
                timeout = os.environ.get("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "10s")
                client = Client(cluster if cluster is not None else scheduler, timeout=timeout)
            except (OSError, TimeoutError, ValueError) as exc:
                raise StereotrackError(f"cannot reach the Dask scheduler at {scheduler} ({_first_line(exc)})") from None
            with client:
                futs = {client.submit(_process_one, *a, pure=False): Path(a[0]).name for a in args}
                for f in as_completed(futs):
                    try:
                        o = f.result()
                    except Exception as exc:  # a worker died, or the cluster lost the task
                        o = ClipOutcome(futs[f], "failed", error=f"Dask: {type(exc).__name__}: {_first_line(exc)}")
                    outcomes[o.clip] = o
                    done += 1
                    if progress is not None:
                        progress(done, len(clips))
        finally:
            if cluster is not None:
                cluster.close()
    ordered = [outcomes[c.name] for c in clips]
    write_summary(out_root, ordered)
    return ordered


def _first_line(exc: BaseException) -> str:
    lines = str(exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def write_summary(out_root: Path, outcomes: list[ClipOutcome]) -> None:
    """``summary.csv`` (one row per clip and method) and ``summary.md``."""
    rows = []
    for o in outcomes:
        methods = o.metrics.get("methods", {}) if o.metrics else {}
        if not methods:
            rows.append((o.clip, o.status, "", "", "", "", "", o.error))
        for m, e in methods.items():
            rows.append((o.clip, o.status, m, e.get("rmse", ""), e.get("final", ""), e.get("reprojection_rmse_px", ""),
                         e.get("steps_per_second", ""), o.error))
    write_csv(out_root / "summary.csv", SUMMARY_COLUMNS, rows)
    n_fail = sum(o.status == "failed" for o in outcomes)
    lines = ["# stereotrack batch summary", "", f"{len(outcomes)} clips, {n_fail} failed.", "",
             "| clip | status | method | 3-D RMSE (m) | final (m) | reproj. RMSE (px) | error |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        fmt = [f"{v:.4g}" if isinstance(v, float) else str(v) for v in r]
        lines.append(f"| {fmt[0]} | {fmt[1]} | {fmt[2]} | {fmt[3]} | {fmt[4]} | {fmt[5]} | {fmt[7]} |")
    write_text(out_root / "summary.md", "\n".join(lines) + "\n")
