"""Batch processing of clip folders: a local process pool by default, a Dask cluster when asked.

Kill-safe by construction: each attempt at a clip writes into its own ``OUT/.<name>.partial-<id>``
folder, writes ``manifest.json`` (sizes and checksums of every output, version, settings) last, and
is swapped into ``OUT/<name>`` only then; a rerun verifies manifests and redoes anything that does
not verify (``force`` redoes everything). Workers die with the batch (:mod:`pipeline.lifeline`),
one batch at a time holds the output folder's lock, and one failing clip is recorded with its
error and never stops the others.
"""

from __future__ import annotations

import concurrent.futures as cf
import json
import multiprocessing as mp
import os
import shutil
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pipeline.camera import has_calibration
from pipeline.errors import StereotrackError
from pipeline.io import ensure_dir, write_csv, write_text
from pipeline.lifeline import OutputLock, die_with_parent, still_parented
from pipeline.manifest import verify_manifest, write_manifest

SUMMARY_COLUMNS = ["clip", "status", "method", "rmse_m", "final_m", "reprojection_rmse_px", "steps_per_second", "error"]


@dataclass
class ClipOutcome:
    clip: str
    status: str  # "ok", "failed", "skipped" (complete from an earlier batch, manifest verified)
    metrics: dict = field(default_factory=dict)
    error: str = ""
    warnings: list[str] = field(default_factory=list)


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


def _worker_init(parent_pid: int, single_thread: bool) -> None:
    """Pool-worker initializer: die with the batch process; one OpenCV thread per worker when
    several workers share the cores."""
    die_with_parent(parent_pid)
    if single_thread:
        import cv2

        cv2.setNumThreads(1)


def _process_one(clip: str, out_root: str, settings: dict[str, Any], parent_pid: int | None = None) -> ClipOutcome:
    """Process one clip into a temporary folder unique to this attempt, write its manifest last,
    and swap it into ``OUT/<name>``. Runs in a pool worker (``parent_pid``: the batch process; a
    worker whose batch has died never commits) or on a Dask worker."""
    import uuid
    import warnings

    from pipeline.clip import resolve_marker_specs
    from pipeline.run import process_clip

    clip_p, name = Path(clip), Path(clip).name
    final = Path(out_root) / name
    partial = Path(out_root) / f".{name}.partial-{uuid.uuid4().hex[:12]}"
    try:
        specs = resolve_marker_specs(clip_p, None, settings.get("markers"))
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            process_clip(clip_p, partial, detector=settings["detector"], methods=settings.get("methods"),
                         images_in_recording=settings.get("images", True), marker_specs=specs,
                         calib_units=settings.get("calib_units"), lock=False, configs=settings.get("configs"))
        write_manifest(partial, settings)
        if parent_pid is not None and not still_parented(parent_pid):
            shutil.rmtree(partial, ignore_errors=True)
            os._exit(1)  # the batch is gone: never commit for a batch that no longer exists
        _swap_in(partial, final)
        notes = sorted({str(w.message) for w in caught})
        return ClipOutcome(name, "ok", json.loads((final / "metrics.json").read_text()), warnings=notes)
    except StereotrackError as exc:
        shutil.rmtree(partial, ignore_errors=True)
        return ClipOutcome(name, "failed", error=str(exc))
    except Exception as exc:
        shutil.rmtree(partial, ignore_errors=True)
        last = traceback.extract_tb(exc.__traceback__)[-1]
        return ClipOutcome(name, "failed", error=f"{type(exc).__name__}: {exc} ({Path(last.filename).name}:{last.lineno})")


def _swap_in(partial: Path, final: Path) -> None:
    """Replace ``final`` by the complete ``partial`` folder with two renames (the old one is moved
    aside first, then deleted), so ``final`` is at every moment either the old or the new output."""
    import uuid

    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.old-{uuid.uuid4().hex[:12]}")
        final.rename(old)
    partial.rename(final)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


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
    scheduler_file: str | Path | None = None,
    configs: dict[str, dict] | None = None,
    images: bool = True,
) -> list[ClipOutcome]:
    """Process every clip under ``input_dir``; write ``summary.csv`` and ``summary.md``.

    ``scheduler``: None for a local process pool; ``"local"`` for a Dask ``LocalCluster`` of
    ``workers`` processes; a ``tcp://host:port`` address (or ``scheduler_file``) for an existing
    Dask scheduler, whose workers must see ``input_dir`` and ``output_dir`` at the same paths.

    ``configs`` (``--config``) are the methods' settings, part of what a complete clip must match.
    ``images``: whether each clip's recording holds its frames (``--no-images`` leaves them out).
    ``marker_specs`` (``--markers``) apply to every clip; else a clip's own ``markers.yaml``, else
    ``INPUT/markers.yaml``, else a rendered clip's description (clip.json) gives its markers.

    The output folder is locked for the whole batch (a second batch on it fails at once, naming
    the holder). A clip counts as done only if its manifest verifies and was made with the same
    settings; anything else (including leftovers of a killed batch) is redone.
    """
    from pipeline.clip import MARKERS_FILE, read_markers_file

    clips = find_clips(input_dir)
    if not clips:
        raise StereotrackError("no clip folders here (a clip holds left/right videos or frame folders and a calibration)",
                               input_dir)
    if not marker_specs and (Path(input_dir) / MARKERS_FILE).is_file():
        marker_specs = read_markers_file(Path(input_dir) / MARKERS_FILE)
    settings = {"detector": detector, "methods": methods, "markers": marker_specs, "calib_units": calib_units,
                "configs": configs, "images": images}
    out_root = ensure_dir(output_dir)
    with OutputLock(out_root, f"stereotrack batch {input_dir}"):
        for stale in [*out_root.glob(".*.partial*"), *out_root.glob(".*.old-*")]:
            shutil.rmtree(stale, ignore_errors=True) if stale.is_dir() else stale.unlink(missing_ok=True)
        outcomes: dict[str, ClipOutcome] = {}
        todo = []
        for c in clips:
            final = out_root / c.name
            if not force and final.is_dir() and verify_manifest(final, settings) is None:
                outcomes[c.name] = ClipOutcome(c.name, "skipped", json.loads((final / "metrics.json").read_text()))
            else:
                todo.append(c)
        done = len(outcomes)
        if progress is not None:
            progress(done, len(clips))

        def record(o: ClipOutcome) -> None:
            nonlocal done
            outcomes[o.clip] = o
            done += 1
            if progress is not None:
                progress(done, len(clips))

        if todo and scheduler is None and scheduler_file is None:
            _run_local(todo, out_root, settings, workers, record)
        elif todo:
            _run_dask(todo, out_root, settings, workers, scheduler, scheduler_file, record)
        ordered = [outcomes[c.name] for c in clips]
        write_summary(out_root, ordered)
    return ordered


def _run_local(todo: list[Path], out_root: Path, settings: dict, workers: int,
               record: Callable[[ClipOutcome], None]) -> None:
    """A spawn-context process pool whose workers die with this process."""
    from concurrent.futures.process import BrokenProcessPool

    init = (os.getpid(), workers > 1)
    with cf.ProcessPoolExecutor(max_workers=max(1, workers), mp_context=mp.get_context("spawn"),
                                initializer=_worker_init, initargs=init) as pool:
        futs = {pool.submit(_process_one, str(c), str(out_root), settings, os.getpid()): c.name for c in todo}
        for f in cf.as_completed(futs):
            try:
                record(f.result())
            except BrokenProcessPool:
                record(ClipOutcome(futs[f], "failed", error="its worker process died (killed, or out of memory)"))


def _run_dask(todo: list[Path], out_root: Path, settings: dict, workers: int, scheduler: str | None,
              scheduler_file: str | Path | None, record: Callable[[ClipOutcome], None]) -> None:
    """On a Dask LocalCluster (``scheduler == "local"``) or an existing scheduler."""
    import logging

    from dask.distributed import Client, LocalCluster, as_completed

    cluster = LocalCluster(n_workers=max(1, workers), threads_per_worker=1, processes=True,
                           dashboard_address=None, silence_logs=logging.WARNING) if scheduler == "local" else None
    where = scheduler_file if scheduler_file is not None else scheduler
    try:
        try:
            # Dask's own setting (DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT) wins; 10 s otherwise
            timeout = os.environ.get("DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT", "10s")
            if cluster is not None:
                client = Client(cluster, timeout=timeout)
            elif scheduler_file is not None:
                if not Path(scheduler_file).is_file():
                    raise StereotrackError("no such Dask scheduler file", scheduler_file)
                client = Client(scheduler_file=str(scheduler_file), timeout=timeout)
            else:
                client = Client(scheduler, timeout=timeout)
        except (OSError, TimeoutError, ValueError) as exc:
            raise StereotrackError(f"cannot reach the Dask scheduler at {where} ({_first_line(exc)})") from None
        with client:
            futs = {client.submit(_process_one, str(c), str(out_root), settings, pure=False): c.name for c in todo}
            for f in as_completed(futs):
                try:
                    o = f.result()
                except Exception as exc:  # a worker died, or the cluster lost the task
                    o = ClipOutcome(futs[f], "failed", error=f"Dask: {type(exc).__name__}: {_first_line(exc)}")
                record(o)
    finally:
        if cluster is not None:
            cluster.close()


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
    notes = [(o.clip, w) for o in outcomes for w in clip_warnings(o)]
    if notes:
        lines += ["", "## Warnings", "", *[f"- **{c}**: {w}" for c, w in notes]]
    write_text(out_root / "summary.md", "\n".join(lines) + "\n")


def clip_warnings(o: ClipOutcome) -> list[str]:
    """A clip's warnings: those raised while processing it, else its failed input checks."""
    if o.warnings:
        return o.warnings
    return [c.get("message", "") for c in (o.metrics or {}).get("checks", []) if not c.get("ok")]
