"""The rerun recording of a run (``out/run.rrd``; rerun-sdk pinned to 0.41), written as a stream.

Entity paths mirror the transform tree: ``/world`` is the left camera's frame; ``/world/left`` and
``/world/right`` carry each camera's ``Transform3D`` (from the calibration) and ``Pinhole``, logged
once as static data, with the frame images (JPEG, logged as they are decoded), detections and
truth projections beneath them. Trajectories live under ``/world/truth`` and
``/world/estimates/<method>`` as one point per marker per frame; the 3-D view shows them over a
visible time range from the start to the cursor, so each path is drawn from its points instead of
being re-logged every frame. Per-frame errors and the target's α and z live under ``/metrics``.
Everything but the images is sent with ``send_columns``: one call per entity, not one per frame,
so memory does not grow with the clip. The blueprint (3-D view, both camera views, error plots) is
built in code and saved as the file's default.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.camera import StereoRig
from pipeline.io import partial_beside
from pipeline.metrics import errors_per_frame
from pipeline.style import TRUTH_RGB, marker_rgb, method_rgb


def blueprint():
    """3-D view (paths: every point from the start to the cursor) beside the two camera views,
    error plots below."""
    import rerun.blueprint as rrb

    trail = rrb.VisibleTimeRange("frame", start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.cursor_relative())
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial3DView(name="3-D", origin="/world", time_ranges=[trail]),
                rrb.Vertical(
                    rrb.Spatial2DView(name="left camera", origin="/world/left"),
                    rrb.Spatial2DView(name="right camera", origin="/world/right"),
                ),
                column_shares=[3, 2],
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(name="3-D error (m)", origin="/metrics/error"),
                rrb.TimeSeriesView(name="reprojection error (px)", origin="/metrics/reprojection"),
                rrb.TimeSeriesView(name="target α (rad)", origin="/metrics/target/alpha"),
                rrb.TimeSeriesView(name="target z (m)", origin="/metrics/target/distance"),
            ),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class Recorder:
    """Writes ``run.rrd`` atomically while a run goes: :meth:`log_frame` for each decoded frame
    pair (compressed at once, never kept), then :meth:`finish` with the calibration and every
    series as columns. Nothing is written at ``path`` until :meth:`finish` succeeds; :meth:`abort`
    (or an exception inside ``with``) leaves no file behind."""

    def __init__(self, path: str | Path, dt: float, jpeg_quality: int = 80, image_every: int = 1) -> None:
        import rerun as rr

        self.path, self.dt = Path(path), float(dt)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = partial_beside(self.path)  # readable like every other output once renamed
        self.quality, self.image_every = int(jpeg_quality), max(1, int(image_every))
        self.rec = None
        try:
            self.rec = rr.RecordingStream("stereotrack")
            self.rec.save(str(self.tmp), default_blueprint=blueprint())
        except BaseException:  # interrupted while opening: leave nothing behind
            self.abort()
            raise
        self.images = 0

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()

    def _time(self, k: int) -> None:
        self.rec.set_time("frame", sequence=k)
        self.rec.set_time("time", duration=k * self.dt)

    def log_frame(self, k: int, left: np.ndarray | None, right: np.ndarray | None) -> None:
        """Both cameras' images of frame ``k`` as JPEG (a missing frame is skipped)."""
        import cv2
        import rerun as rr

        if k % self.image_every:
            return
        self._time(k)
        for img, name in ((left, "left"), (right, "right")):
            if img is not None:
                ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
                if ok:
                    self.rec.log(f"world/{name}/image", rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
                    self.images += 1

    def _columns(self, entity: str, frames: np.ndarray, columns) -> None:
        import rerun as rr

        if len(frames):
            self.rec.send_columns(entity, indexes=[rr.TimeColumn("frame", sequence=frames),
                                                   rr.TimeColumn("time", duration=frames * self.dt)],
                                  columns=columns)

    def _points(self, entity: str, per_frame: list[np.ndarray], colours: list[list], labels: list[list] | None,
                kind: str, radius: float) -> None:
        """One batch of points per frame (frames with none are skipped), as partitioned columns."""
        import rerun as rr

        frames = np.array([k for k, p in enumerate(per_frame) if len(p)], dtype=np.int64)
        if not len(frames):
            return
        lengths = [len(per_frame[k]) for k in frames]
        pos = np.concatenate([per_frame[k] for k in frames])
        col = np.concatenate([np.asarray(colours[k], dtype=np.uint8).reshape(-1, 3) for k in frames])
        arch = rr.Points3D if kind == "3d" else rr.Points2D
        kw = {"labels": [x for k in frames for x in labels[k]]} if labels is not None else {}
        cols = arch.columns(positions=pos, colors=col, radii=np.full(len(pos), radius, np.float32), **kw)
        self._columns(entity, frames, cols.partition(lengths))

    def _scalars(self, entity: str, series: np.ndarray) -> None:
        import rerun as rr

        series = np.asarray(series, dtype=float)
        ok = np.flatnonzero(np.isfinite(series))
        self._columns(entity, ok.astype(np.int64), rr.Scalars.columns(scalars=series[ok]))

    def finish(self, rig: StereoRig, observations: dict[str, np.ndarray], tracks: dict[str, dict],
               truth: dict[str, np.ndarray] | None = None, extra_series: dict[str, np.ndarray] | None = None,
               marker_colours: dict[str, list[int]] | None = None,
               progress: Callable[[int, int], None] | None = None) -> Path:
        """Log the calibration (static), detections, truth, every method's points and every series
        as columns, then move the file into place; ``progress`` gets (methods done, methods)."""
        import rerun as rr

        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RDF, static=True)  # OpenCV axes: x right, y down, z forward
        w, h = rig.image_size
        for cam, name in zip(rig.cameras, ("left", "right"), strict=True):
            rec.log(f"world/{name}", rr.Transform3D(translation=cam.center, mat3x3=cam.R.T), static=True)
            rec.log(f"world/{name}", rr.Pinhole(image_from_camera=cam.K, width=w or None, height=h or None,
                                               camera_xyz=rr.ViewCoordinates.RDF), static=True)
        markers = list(observations)
        mcol = {m: list(marker_rgb(marker_colours or {}, m, i)) for i, m in enumerate(markers)}
        n = max([len(v) for v in observations.values()] + [len(t.position) for per in tracks.values()
                                                             for t in per.values()] + [0])
        for c, name in enumerate(("left", "right")):
            pts, cols, labs = [], [], []
            for k in range(n):
                here = [m for m in markers
                        if k < len(observations[m]) and np.all(np.isfinite(observations[m][k, 2 * c:2 * c + 2]))]
                pts.append(np.array([observations[m][k, 2 * c:2 * c + 2] for m in here]).reshape(-1, 2))
                cols.append([mcol[m] for m in here])
                labs.append(here)
            self._points(f"world/{name}/detections", pts, cols, labs, "2d", 3.0)
            if truth is not None:
                tp = [np.array([truth[m][k] for m in markers if m in truth and k < len(truth[m])]).reshape(-1, 3)
                      for k in range(n)]
                proj = [rig.cameras[c].project(p) if len(p) else p[:, :2] for p in tp]
                self._points(f"world/{name}/truth", proj, [[TRUTH_RGB] * len(p) for p in proj], None, "2d", 2.0)
        if truth is not None:
            tp = [np.array([truth[m][k] for m in markers if m in truth and k < len(truth[m])]).reshape(-1, 3)
                  for k in range(n)]
            self._points("world/truth/points", tp, [[TRUTH_RGB] * len(p) for p in tp], None, "3d", 0.012)
        for j, (meth, per_marker) in enumerate(tracks.items()):
            if progress is not None:
                progress(j, len(tracks))
            rgb = list(method_rgb(meth))
            cur = [np.array([t.position[k] for t in per_marker.values() if k < len(t.position)
                             and np.all(np.isfinite(t.position[k]))]).reshape(-1, 3) for k in range(n)]
            self._points(f"world/estimates/{meth}/points", cur, [[rgb] * len(p) for p in cur], None, "3d", 0.01)
            for marker, t in per_marker.items():
                if truth is not None and marker in truth:
                    self._scalars(f"metrics/error/{meth}/{marker}", errors_per_frame(t.position, truth[marker]))
                self._scalars(f"metrics/reprojection/{meth}/{marker}", t.reprojection_error)
        for key, series in (extra_series or {}).items():
            self._scalars(f"metrics/{key}", series)
        rec.flush()
        rec.disconnect()
        os.replace(self.tmp, self.path)
        return self.path

    def abort(self) -> None:
        """Stop recording and remove the partial file (after the file sink has closed it, so that
        no late write recreates it)."""
        try:
            if self.rec is not None:
                self.rec.disconnect()
        finally:
            self.tmp.unlink(missing_ok=True)


def write_recording(path: str | Path, rig: StereoRig, dt: float, observations: dict[str, np.ndarray],
                    tracks: dict[str, dict], truth: dict[str, np.ndarray] | None = None, frames=None,
                    extra_series: dict[str, np.ndarray] | None = None,
                    marker_colours: dict[str, list[int]] | None = None) -> Path:
    """A recording in one call: ``frames`` optionally yields (index, left, right) BGR images, which
    are logged as they come."""
    with Recorder(path, dt) as rec:
        for k, left, right in frames or ():
            rec.log_frame(k, left, right)
        return rec.finish(rig, observations, tracks, truth, extra_series, marker_colours)
