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

#: 3-D sizes (m): truth small and black, each method's points larger in its colour, paths thin
TRUTH_RADIUS, POINT_RADIUS, PATH_RADIUS = 0.005, 0.008, 0.002


def blueprint(fps: float = 30.0, target: bool = False, info: bool = False):
    """3-D view (paths: every point from the start to the cursor) beside the two camera views,
    error plots below; the four-point target's α and z plots only when the run has the target, the
    run's description when given. The time panel opens on the ``frame`` timeline at the clip's
    frame rate (on rerun's default ``time`` timeline the trail is empty: it is set for ``frame``)."""
    import rerun.blueprint as rrb

    trail = rrb.VisibleTimeRange("frame", start=rrb.TimeRangeBoundary.infinite(),
                                 end=rrb.TimeRangeBoundary.cursor_relative())
    plots = [rrb.TimeSeriesView(name="3-D error (m)", origin="/metrics/error"),
             rrb.TimeSeriesView(name="reprojection error (px)", origin="/metrics/reprojection")]
    if target:
        plots += [rrb.TimeSeriesView(name="target α (rad)", origin="/metrics/target/alpha"),
                  rrb.TimeSeriesView(name="target z (m)", origin="/metrics/target/distance")]
    side = [rrb.Spatial2DView(name="left camera", origin="/world/left"),
            rrb.Spatial2DView(name="right camera", origin="/world/right")]
    if info:
        side.append(rrb.TextDocumentView(name="this run", origin="/run"))
    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(rrb.Spatial3DView(name="3-D", origin="/world", time_ranges=[trail]), rrb.Vertical(*side),
                           column_shares=[3, 2]),
            rrb.Horizontal(*plots),
            row_shares=[3, 2],
        ),
        rrb.TimePanel(timeline="frame", fps=float(fps), play_state="paused"),
        collapse_panels=True,
    )


class Recorder:
    """Writes ``run.rrd`` atomically while a run goes: :meth:`log_frame` for each decoded frame
    pair (compressed at once, never kept), then :meth:`finish` with the calibration and every
    series as columns. Nothing is written at ``path`` until :meth:`finish` succeeds; :meth:`abort`
    (or an exception inside ``with``) leaves no file behind."""

    def __init__(self, path: str | Path, dt: float, jpeg_quality: int = 80, image_every: int = 1,
                 name: str | None = None) -> None:
        import rerun as rr

        self.path, self.dt, self.name = Path(path), float(dt), name
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = partial_beside(self.path)  # readable like every other output once renamed
        self.quality, self.image_every = int(jpeg_quality), max(1, int(image_every))
        self.rec = None
        try:
            self.rec = rr.RecordingStream("stereotrack")
            self.rec.save(str(self.tmp))  # the blueprint, chosen for this run, is sent by finish
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

    def _scalars(self, entity: str, series: np.ndarray, name: str | None = None, rgb=None) -> None:
        """A scalar series as columns, named and coloured (static ``SeriesLines``) as the report draws it."""
        import rerun as rr

        series = np.asarray(series, dtype=float)
        ok = np.flatnonzero(np.isfinite(series))
        if name is not None:
            self.rec.log(entity, rr.SeriesLines(names=[name], colors=[list(rgb)], widths=[1.5]), static=True)
        self._columns(entity, ok.astype(np.int64), rr.Scalars.columns(scalars=series[ok]))

    def _paths(self, entity: str, tracks: list[np.ndarray], rgb) -> None:
        """Each track as a static 3-D line strip (split where it has no estimate): the whole path
        at a glance, whatever the time cursor."""
        import rerun as rr

        strips = []
        for P in tracks:
            ok = np.all(np.isfinite(P), axis=1)
            edges = np.flatnonzero(np.diff(np.r_[0, ok.astype(int), 0]))
            strips += [P[a:b] for a, b in zip(edges[::2], edges[1::2], strict=True) if b - a >= 2]
        if strips:
            self.rec.log(entity, rr.LineStrips3D(strips, colors=[list(rgb)] * len(strips),
                                                 radii=[PATH_RADIUS] * len(strips)), static=True)

    def finish(self, rig: StereoRig, observations: dict[str, np.ndarray], tracks: dict[str, dict],
               truth: dict[str, np.ndarray] | None = None, extra_series: dict[str, np.ndarray] | None = None,
               marker_colours: dict[str, list[int]] | None = None,
               progress: Callable[[int, int], None] | None = None, info: str | None = None) -> Path:
        """Log the calibration (static), detections, truth, every method's points, path and named,
        coloured series, the run's description (``info``, Markdown) and the blueprint for this run,
        then move the file into place; ``progress`` gets (methods done, methods)."""
        import rerun as rr

        rec = self.rec
        if self.name:
            rec.send_recording_name(self.name)
        if info:
            rec.log("run", rr.TextDocument(info, media_type=rr.MediaType.MARKDOWN), static=True)
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
            self._points("world/truth/points", tp, [[TRUTH_RGB] * len(p) for p in tp], None, "3d", TRUTH_RADIUS)
            self._paths("world/truth/path", [truth[m] for m in markers if m in truth], TRUTH_RGB)
        for j, (meth, per_marker) in enumerate(tracks.items()):
            if progress is not None:
                progress(j, len(tracks))
            rgb = list(method_rgb(meth))
            here = [[m for m, t in per_marker.items() if k < len(t.position) and np.all(np.isfinite(t.position[k]))]
                    for k in range(n)]
            cur = [np.array([per_marker[m].position[k] for m in ms]).reshape(-1, 3) for k, ms in enumerate(here)]
            colours = [[rgb] * len(p) for p in cur]
            self._points(f"world/estimates/{meth}/points", cur, colours, here, "3d", POINT_RADIUS)
            for c, cam in enumerate(("left", "right")):  # the estimates seen through each camera
                seen = [rig.cameras[c].project(p) if len(p) else p[:, :2] for p in cur]
                self._points(f"world/{cam}/estimates/{meth}", seen, colours, here, "2d", 2.5)
            self._paths(f"world/estimates/{meth}/path", [t.position for t in per_marker.values()], rgb)
            for marker, t in per_marker.items():
                if truth is not None and marker in truth:
                    self._scalars(f"metrics/error/{meth}/{marker}", errors_per_frame(t.position, truth[marker]),
                                  f"{meth} · {marker}", rgb)
                self._scalars(f"metrics/reprojection/{meth}/{marker}", t.reprojection_error, f"{meth} · {marker}", rgb)
        for key, series in (extra_series or {}).items():
            who = key.rsplit("/", 1)[-1]
            self._scalars(f"metrics/{key}", series, who, list(TRUTH_RGB if who == "truth" else method_rgb(who)))
        if progress is not None:
            progress(len(tracks), len(tracks))  # the bar completes (it stopped at n − 1 of n)
        target = any(k.startswith("target/") for k in extra_series or {})
        rec.send_blueprint(blueprint(1.0 / self.dt, target, bool(info)), make_active=True, make_default=True)
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
