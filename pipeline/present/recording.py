"""The rerun recording of a run (``out/run.rrd``; rerun-sdk pinned to 0.41), written as a stream.

Entity paths mirror the transform tree: ``/world`` is the left camera's frame; ``/world/left`` and
``/world/right`` carry each camera's ``Transform3D`` (from the calibration) and ``Pinhole``, logged
once as static data, with the frame images (JPEG as decoded; an H.264 camera's video once, referenced
frame by frame), detections (rings), truth projections (small rings) and each method's reprojection (crosses)
beneath them. Trajectories live under ``/world/truth`` and
``/world/estimates/<method>`` as one point per marker per frame (an empty batch where a track
ends), shown at the cursor over each one's static path, framed on the tracks and not the cameras,
the best three methods shown and the rest one click away; filters' 95 % position ellipsoids under
``/world/uncertainty/<method>`` (hidden until shown). Per-frame errors live under
``/metrics/<error|reprojection>/<marker>/<method>``, the filters' depth error with its ±σ band under
``/metrics/depth``, each track's state lane under ``/state``, the target's α and z under ``/metrics/target``.
Everything but the images is sent with ``send_columns``: one call per entity, not one per frame,
so memory does not grow with the clip. The blueprint (3-D view, both camera views, error plots;
:mod:`pipeline.present.layout`) is built in code and saved as the file's default.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.errors import StereotrackError
from pipeline.core.interrupts import raise_if_interrupted
from pipeline.core.io import partial_beside
from pipeline.core.rig import Rig
from pipeline.evaluation.identity import switches_of
from pipeline.evaluation.metrics import ranking, runaways
from pipeline.evaluation.scores import FrameScores
from pipeline.present.layout import SHOWN_METHODS, blueprint, framing
from pipeline.present.shapes import crosses, ellipsoid_columns, pane_width, rings
from pipeline.present.sink import check_reads_back as _check_reads_back
from pipeline.present.sink import flushed
from pipeline.present.states import STATES, frame_states, transitions
from pipeline.present.style import TRUTH_RGB_VIEWER, marker_rgb, method_rgb

if TYPE_CHECKING:
    from pipeline.estimate import EstimateResult
    from pipeline.estimators import Track

#: 3-D sizes in UI points (negative: rerun's screen-space radii, the same size at any zoom): truth
#: small and light grey inside each method's larger sphere in its colour, paths thin
TRUTH_RADIUS, POINT_RADIUS, PATH_RADIUS = -3.0, -5.0, -1.0
#: camera panes, as fractions of the image's width (the pane scales the image to fit, so these are
#: what decides the size on screen): a detection's ring, the truth's smaller ring, a method's cross
#: (half its arm, reaching past the ring); line widths in UI points (negative: the same at any zoom)
DETECTION_RING, TRUTH_RING, CROSS_ARM, LINE_WIDTH = 0.02, 0.008, 0.03, -1.5
#: the plotted methods' line widths (UI points) in drawing order: a method whose series lies on
#: another's still shows, as a thin line inside a wider one
SERIES_WIDTHS = (3.5, 2.0, 1.0)
#: video codecs (FFmpeg's tags) the viewer decodes in every build: H.264; MPEG-4 Part 2 it cannot
VIEWER_CODECS = frozenset({"avc1", "h264"})


@dataclass
class _Batches:
    """Points logged per frame, frame-major: the frames that have any, how many each has, the
    points in order (each frame's in its tracks' order) and which track each came from."""

    frames: np.ndarray
    lengths: np.ndarray
    points: np.ndarray
    which: np.ndarray


def _batches(tracks: list[np.ndarray], n: int, finite: bool = True) -> _Batches:
    """Per frame ``k < n``, the rows ``k`` of the ``tracks`` (each frames × d) that exist there (and,
    with ``finite``, hold no NaN), as arrays: a whole clip at once, no per-frame Python objects."""
    d = tracks[0].shape[1] if tracks else 3
    A = np.full((n, len(tracks), d), np.nan)
    ok = np.zeros((n, len(tracks)), dtype=bool)
    for j, t in enumerate(tracks):
        m = min(n, len(t))
        A[:m, j] = t[:m]
        ok[:m, j] = np.isfinite(t[:m]).all(axis=1) if finite else True
    rows, cols = np.nonzero(ok)  # row-major: frame by frame, tracks in order
    counts = np.bincount(rows, minlength=n)
    keep = _logged_frames(counts)
    return _Batches(keep, counts[keep], A[rows, cols], cols)


def _logged_frames(counts: np.ndarray) -> np.ndarray:
    """The frames to log given each frame's count of points: those with points, and an empty batch
    where the last ones went (the views show the latest batch at the cursor, so a track that ended
    is not left standing where it was last seen)."""
    return np.flatnonzero((counts > 0) | (np.r_[False, counts[:-1] > 0] & (counts == 0))).astype(np.int64)


def _frames(est: EstimateResult) -> int:
    """The frames a run's series span: the clip's, or its longest observations'."""
    return max([len(v) for v in est.observations.values()] + [est.n_frames])


class Recorder:
    """Writes ``run.rrd`` atomically while a run goes: :meth:`log_frame` for each decoded frame
    pair (compressed at once, never kept), then :meth:`finish` with the calibration and every
    series as columns. Nothing is written at ``path`` until :meth:`finish` succeeds; :meth:`abort`
    (or an exception inside ``with``) leaves no file behind. ``app``: the rerun application id, one
    per clip (the viewer keeps one blueprint per application)."""

    def __init__(self, path: str | Path, dt: float, jpeg_quality: int = 80, image_every: int = 1,
                 name: str | None = None, cameras: tuple[str, ...] = ("left", "right"), app: str | None = None) -> None:
        os.environ.setdefault("RUST_LOG", "off")  # the file sink's own log lines (a full disk): ours name the file
        import rerun as rr

        self.path, self.dt, self.name, self.cameras = Path(path), float(dt), name, tuple(cameras)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.rec: Any = None
        self.stalled = False  # the sink stopped writing (pipeline.present.sink.flushed)
        self.tmp = partial_beside(self.path)  # readable like every other output once renamed
        try:  # interrupted anywhere from here to the end of construction: leave nothing behind
            self.quality, self.image_every = int(jpeg_quality), max(1, int(image_every))
            # an application per clip: the viewer keeps one blueprint per application, and a batch's
            # clips opened together (`stereotrack view OUT`) would otherwise all show the last one's layout
            self.rec = rr.RecordingStream(app or "stereotrack")
            self.rec.save(str(self.tmp))  # the blueprint, chosen for this run, is sent by finish
            self.images = 0
            self.logged: list[str] = []  # point methods logged so far (by :meth:`method`)
            self.uncertain: list[str] = []  # those of them with covariance ellipsoids
            self.extent: dict[str, list[np.ndarray]] = {}  # each method's paths in its 2–98 % box (framing without truth)
            self.markers: set[str] = set()
            self.banded: set[str] = set()  # markers with a filter's depth error and ±σ band
            self.series: dict[str, tuple[str, list]] = {}  # a plotted method series → its name and colour
            self.videos: set[str] = set()  # cameras whose video file is referenced (no JPEG copies)
        except BaseException:
            self.abort()
            raise

    def __enter__(self) -> Recorder:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.abort()

    def _time(self, k: int) -> None:
        self.rec.set_time("frame", sequence=k)
        self.rec.set_time("time", duration=k * self.dt)

    def reference_video(self, camera: str, path: Path) -> bool:
        """Log ``camera``'s video file itself, once (``AssetVideo``: its H.264 stream, not a JPEG copy
        of every frame), and a reference to each of its frames on the ``frame`` timeline (frame k:
        the k-th in presentation order, as the detect stage decodes them). False, logging nothing,
        for a codec the viewer cannot decode everywhere (MPEG-4 Part 2, as rendered clips are):
        :meth:`log_frame` then logs that camera's frames as JPEG."""
        import rerun as rr

        from pipeline.core.frames import video_codec

        if video_codec(path) not in VIEWER_CODECS:
            return False
        asset = rr.AssetVideo(path=path)
        entity = f"world/{camera}/video"
        self.rec.log(entity, asset, static=True)
        ts = np.asarray(asset.read_frame_timestamps_nanos(), dtype=np.int64)
        k = np.arange(len(ts), dtype=np.int64)
        self.rec.send_columns(entity, indexes=[rr.TimeColumn("frame", sequence=k), rr.TimeColumn("time", duration=k * self.dt)],
                              columns=rr.VideoFrameReference.columns_nanos(ts))
        self.videos.add(camera)
        return True

    def log_frame(self, k: int, *images: np.ndarray | None) -> None:
        """Every camera's image of frame ``k`` as JPEG, in :attr:`cameras`' order (a missing frame
        is skipped, and so is a camera whose video is referenced: :meth:`reference_video`)."""
        self.log_encoded(k, *(self.encode(c, k, img) for c, img in enumerate(images)))

    def encode(self, camera: int, k: int, img: np.ndarray | None) -> bytes | None:
        """Camera ``camera``'s image of frame ``k`` as the JPEG :meth:`log_encoded` logs (None where
        nothing is logged). Touches no rerun state: a camera's detection process encodes its own
        frames (:class:`~pipeline.core.settings.RunHooks` ``image``)."""
        import cv2

        if img is None or k % self.image_every or camera >= len(self.cameras) or self.cameras[camera] in self.videos:
            return None
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, self.quality])
        return buf.tobytes() if ok else None

    def log_encoded(self, k: int, *jpegs: bytes | None) -> None:
        """Frame ``k``'s JPEGs from :meth:`encode`, one per camera in :attr:`cameras`' order."""
        import rerun as rr

        if k % self.image_every:
            return
        self._time(k)
        for buf, name in zip(jpegs, self.cameras, strict=False):
            if buf is not None:
                self.rec.log(f"world/{name}/image", rr.EncodedImage(contents=buf, media_type="image/jpeg"))
                self.images += 1

    def _columns(self, entity: str, frames: np.ndarray, columns) -> None:
        import rerun as rr

        if len(frames):
            self.rec.send_columns(entity, indexes=[rr.TimeColumn("frame", sequence=frames),
                                                   rr.TimeColumn("time", duration=frames * self.dt)],
                                  columns=columns)

    def _points(self, entity: str, batches: _Batches, colours: np.ndarray, labels: list[str] | None, kind: str,
                radius: float, show_labels: bool = True) -> None:
        """One batch of points per frame (frames with none are skipped), as partitioned columns;
        ``colours``: one RGB per point; labels not drawn when ``show_labels`` is False (still shown
        on hover and selection)."""
        import rerun as rr

        if not len(batches.frames):
            return
        arch = rr.Points3D if kind == "3d" else rr.Points2D
        if labels is not None and not show_labels:
            self.rec.log(entity, arch.from_fields(show_labels=False), static=True)
        cols = arch.columns(positions=batches.points, colors=np.asarray(colours, dtype=np.uint8).reshape(-1, 3),
                            radii=np.full(len(batches.points), radius, np.float32), labels=labels)
        self._columns(entity, batches.frames, cols.partition(batches.lengths.tolist()))

    def _strips2d(self, entity: str, batches: _Batches, colours: np.ndarray, labels: list[str] | None, shape: str,
                  size: float) -> None:
        """Each point of ``batches`` drawn as a ring (``shape`` "ring") or a cross ("cross") of ``size`` image
        pixels, one batch per frame as partitioned columns; labels shown on hover only."""
        import rerun as rr

        if not len(batches.frames):
            return
        per = 1 if shape == "ring" else 2
        strips = rings(batches.points, size) if shape == "ring" else crosses(batches.points, size)
        rgb = np.repeat(np.asarray(colours, dtype=np.uint8).reshape(-1, 3), per, axis=0)
        if labels is not None:
            labels = [lab for lab in labels for _ in range(per)]
            self.rec.log(entity, rr.LineStrips2D.from_fields(show_labels=False), static=True)
        # the strips as one n × k × 2 array: rerun's numpy path (one conversion; a list converts strip by strip,
        # 40 µs each: 2 s of `run`'s recording on the default clip), the same arrow data (tests/pipeline/test_pipeline.py)
        cols = rr.LineStrips2D.columns(strips=strips, colors=rgb, radii=np.full(len(strips), LINE_WIDTH, np.float32),
                                       labels=labels)
        self._columns(entity, batches.frames, cols.partition((per * batches.lengths).tolist()))

    def _scalars(self, entity: str, series: np.ndarray, name: str | None = None, rgb=None) -> None:
        """A scalar series as columns, named and coloured (static ``SeriesLines``) as the report draws it."""
        import rerun as rr

        series = np.asarray(series, dtype=float)
        ok = np.flatnonzero(np.isfinite(series))
        if name is not None:
            self.rec.log(entity, rr.SeriesLines(names=[name], colors=[list(rgb)], widths=[1.5]), static=True)
            self.series[entity] = (name, list(rgb))
        self._columns(entity, ok.astype(np.int64), rr.Scalars.columns(scalars=series[ok]))

    def _widths(self, shown: list[str]) -> None:
        """The shown methods' series in :data:`SERIES_WIDTHS`, widest first in the viewer's drawing
        order (by entity path: by name), so that each is drawn over a wider one."""
        import rerun as rr

        order = sorted(shown)
        for entity, (name, rgb) in self.series.items():
            if name in order:
                width = SERIES_WIDTHS[min(order.index(name), len(SERIES_WIDTHS) - 1)]
                self.rec.log(entity, rr.SeriesLines(names=[name], colors=[rgb], widths=[width]), static=True)

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

    def method(self, est: EstimateResult, meth: str, per_marker: dict[str, Track], scores: dict[str, FrameScores]) -> None:
        """One point method's points, path, covariance ellipsoids and named, coloured series, as
        soon as the method has run (its tracks need not be kept for :meth:`finish`)."""
        n = _frames(est)
        self._method(est.rig, meth, per_marker, scores, n)
        self._track_events(meth, per_marker, scores)
        self._states(meth, per_marker)
        self._depth_bands(meth, per_marker, est.truth_positions or {})
        if self._ellipsoids(meth, per_marker, n):
            self.uncertain.append(meth)
        P = np.vstack([t.position for t in per_marker.values()] or [np.empty((0, 3))])
        if np.isfinite(P).all(axis=1).sum() >= 2:  # its paths inside its 2–98 % box grown by a tenth each
            lo, hi = np.nanpercentile(P[np.isfinite(P).all(axis=1)], [2, 98], axis=0)  # way: to frame without truth
            lo, hi = lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo)
            self.extent[meth] = [np.clip(t.position[:, :3], lo, hi) for t in per_marker.values()]
        self.logged.append(meth)
        self.markers.update(per_marker)

    def _track_events(self, meth: str, per_marker: dict[str, Track], scores: dict[str, FrameScores]) -> None:
        """A group's tracks (``<group>#<n>``) as events on the timeline under ``/events/<method>``:
        each track's birth (its first estimate) and end (its last), and with truth each identity
        switch (the track starts to follow another marker), as text-log entries."""
        import rerun as rr

        events = []
        for name, t in per_marker.items():
            live = np.flatnonzero(np.all(np.isfinite(t.position), axis=1))
            if "#" in name and len(live):
                events += [(int(live[0]), "INFO", f"{name} born"), (int(live[-1]), "INFO", f"{name} ended")]
            follows = scores[name].follows if name in scores else None
            events += [(k, "WARN", f"{name}: identity switch, follows {now} (was {was})")
                       for k, was, now in switches_of(follows or [])]
        if events:
            events.sort()
            cols = rr.TextLog.columns(text=[e[2] for e in events], level=[e[1] for e in events])
            self._columns(f"events/{meth}", np.array([e[0] for e in events], dtype=np.int64), cols)

    def _depth_bands(self, meth: str, per_marker: dict[str, Track], truth: dict[str, np.ndarray]) -> None:
        """A filter's signed depth error against the truth (mm) with its own ±σ as a band
        (``Measurements``: σ² = the covariance's depth entry) under ``/metrics/depth/<marker>/<method>``:
        a consistent filter's error stays inside its band about two frames in three."""
        import rerun as rr

        for marker, t in per_marker.items():
            if t.covariance is None or marker not in truth:
                continue
            m = min(len(t.position), len(truth[marker]))
            err, var = 1000.0 * (t.position[:m, 2] - np.asarray(truth[marker], dtype=float)[:m, 2]), 1e6 * t.covariance[:m, 2, 2]
            ok = np.flatnonzero(np.isfinite(err) & np.isfinite(var))
            if len(ok) == 0:
                continue
            entity = f"metrics/depth/{marker}/{meth}"
            style = rr.Measurements.from_fields(names=[meth], colors=[list(method_rgb(meth))], units=["mm"])
            self.rec.log(entity, style, static=True)
            self._columns(entity, ok.astype(np.int64), rr.Measurements.columns(values=err[ok], variances=var[ok]))
            self.banded.add(marker)

    def _states(self, meth: str, per_marker: dict[str, Track]) -> None:
        """Each track's state lane under ``/state/<method>/<marker>`` (:mod:`~pipeline.present.states`): a
        ``StateChange`` at every transition, coloured and labelled by a static ``StateConfiguration``."""
        import rerun as rr

        config = rr.StateConfiguration(values=list(STATES), labels=list(STATES), colors=[list(c) for c in STATES.values()])
        for marker, t in per_marker.items():
            frames, values = transitions(frame_states(t.position, t.predicted, t.extra))
            if len(frames):
                self.rec.log(f"state/{meth}/{marker}", config, static=True)
                self._columns(f"state/{meth}/{marker}", frames, rr.StateChange.columns(state=values))

    def finish(self, est: EstimateResult, marker_colours: dict[str, list[int]] | None = None,
               progress: Callable[[int, int], None] | None = None, info: str | None = None) -> Path:
        """Log the calibration (static), detections, truth, each method of ``est.tracks`` not
        logged yet by :meth:`method`, the target's plate and centres, the run's description
        (``info``, Markdown) and the blueprint for this run, then move the file into place;
        ``progress`` gets (methods done, methods)."""
        import rerun as rr

        if self.name:
            self.rec.send_recording_name(self.name)
        if info:
            self.rec.log("run", rr.TextDocument(info, media_type=rr.MediaType.MARKDOWN), static=True)
        self._rig(est.rig)
        self._detections(est, marker_colours or {}, est.truth_positions, _frames(est))
        todo = [m for m in est.tracks if m not in self.logged]
        for j, meth in enumerate(todo):
            if progress is not None:
                progress(j, len(todo))
            self.method(est, meth, est.tracks[meth], est.scores[meth])
        self._target(est, est.truth_positions, _frames(est))
        if progress is not None:  # the bar completes: n of n, or 1 of 1 when every method was logged as it finished
            progress(max(len(todo), 1), max(len(todo), 1))
        lost = runaways(est.metrics)
        best = [m for m in ranking(est.metrics) if m not in lost and m in self.logged]
        self._widths(best[:SHOWN_METHODS])
        if not est.truth_positions and best:  # no truth to name the markers in 3-D: the best method's points do
            self.rec.log(f"world/estimates/{best[0]}/points", rr.Points3D.from_fields(show_labels=True), static=True)
        self.rec.send_blueprint(blueprint(1.0 / self.dt, bool(est.target_tracks), bool(info), sorted(self.markers),
                                          lost, self.uncertain, est.rig.names, tucked=best[SHOWN_METHODS:],
                                          eye=self._eye(est, best), truth=bool(est.truth_positions),
                                          camera_off=[m for m in self.logged if m not in best[:1]],
                                          banded=sorted(self.banded)),
                                make_active=True, make_default=True)
        self.stalled = not flushed(self.rec, self.tmp)
        if self.stalled:
            raise StereotrackError("the recording could not be written completely (its file stopped growing; is the disk full?)",
                                   self.path)
        self.rec.disconnect()
        _check_reads_back(self.tmp, self.path)
        raise_if_interrupted()  # nothing is committed once a signal came
        os.replace(self.tmp, self.path)
        return self.path

    def _eye(self, est: EstimateResult, best: list[str]) -> tuple[np.ndarray, np.ndarray] | None:
        """The 3-D view's eye, framed on the truth's paths, else on the best method's (inside its
        2–98 % box grown by a tenth: a diverging stretch does not set the view)."""
        if est.truth_positions:
            return framing([np.asarray(p, dtype=float)[:, :3] for p in est.truth_positions.values()])
        return framing(self.extent[best[0]]) if best and best[0] in self.extent else None

    def _rig(self, rig: StereoRig | Rig) -> None:
        """Every camera as a static transform and pinhole in OpenCV's axes."""
        import rerun as rr

        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)  # x right, y down, z forward
        for cam, name, (w, h) in zip(rig.cameras, rig.names, rig.sizes, strict=True):
            self.rec.log(f"world/{name}", rr.Transform3D(translation=cam.center, mat3x3=cam.R.T), static=True)
            self.rec.log(f"world/{name}", rr.Pinhole(image_from_camera=cam.K, width=w or None, height=h or None,
                                                    camera_xyz=rr.ViewCoordinates.RDF), static=True)

    def _detections(self, est: EstimateResult, colours: dict[str, list[int]], truth: dict | None, n: int) -> None:
        """Each camera's detections (marker colours, labelled) and truth projections; truth in 3-D."""
        obs, markers = est.observations, list(est.observations)
        mcol = np.array([marker_rgb(colours, m, i) for i, m in enumerate(markers)], dtype=np.uint8).reshape(-1, 3)
        there = [m for m in markers if truth is not None and m in truth]
        tp = _batches([truth[m] for m in there], n, finite=False) if truth is not None else None
        for c, name in enumerate(est.rig.names):
            det, w = _batches([obs[m][:, 2 * c : 2 * c + 2] for m in markers], n), pane_width(est.rig, c)
            self._strips2d(f"world/{name}/detections", det, mcol[det.which], [markers[j] for j in det.which], "ring",
                           DETECTION_RING * w)  # labels on hover: drawn, they cover the blobs at the pane's size
            if tp is not None:
                proj = _Batches(tp.frames, tp.lengths, est.rig.cameras[c].project(tp.points), tp.which)
                self._strips2d(f"world/{name}/truth", proj, np.tile(TRUTH_RGB_VIEWER, (len(proj.points), 1)), None, "ring",
                               TRUTH_RING * w)
        if truth is not None and tp is not None:
            self._points("world/truth/points", tp, np.tile(TRUTH_RGB_VIEWER, (len(tp.points), 1)),
                         [there[j] for j in tp.which], "3d", TRUTH_RADIUS)
            self._paths("world/truth/path", [truth[m] for m in markers if m in truth], TRUTH_RGB_VIEWER)

    def _method(self, rig: StereoRig | Rig, meth: str, per_marker: dict, scores: dict[str, FrameScores], n: int) -> None:
        """A method's labelled points in 3-D and through each camera, its path, and its error
        series per marker (``/metrics/<kind>/<marker>/<method>``, named and coloured)."""
        rgb = list(method_rgb(meth))
        names = list(per_marker)
        cur = _batches([per_marker[m].position for m in names], n)
        colours, labels = np.tile(rgb, (len(cur.points), 1)), [names[j] for j in cur.which]
        self._points(f"world/estimates/{meth}/points", cur, colours, labels, "3d", POINT_RADIUS, show_labels=False)
        for c, cam in enumerate(rig.names):  # the estimates seen through each camera
            seen = _Batches(cur.frames, cur.lengths, rig.cameras[c].project(cur.points), cur.which)
            self._strips2d(f"world/{cam}/estimates/{meth}", seen, colours, labels, "cross", CROSS_ARM * pane_width(rig, c))
        self._paths(f"world/estimates/{meth}/path", [t.position for t in per_marker.values()], rgb)
        for marker, t in per_marker.items():
            if (error := scores[marker].error) is not None:
                self._scalars(f"metrics/error/{marker}/{meth}", 1000.0 * error, meth, rgb)  # mm, as the report
            self._scalars(f"metrics/reprojection/{marker}/{meth}", t.reprojection_error, meth, rgb)

    def _ellipsoids(self, meth: str, per_marker: dict, n: int) -> bool:
        """The 95 % position ellipsoid of each marker per frame (filters with a covariance)."""
        import rerun as rr

        tracks = [t for t in per_marker.values() if t.covariance is not None]
        pos, cov = np.full((n, len(tracks), 3), np.nan), np.full((n, len(tracks), 3, 3), np.nan)
        for j, t in enumerate(tracks):
            m = min(n, len(t.position))
            pos[:m, j], cov[:m, j] = t.position[:m], t.covariance[:m, :3, :3]
        ok = np.isfinite(pos).all(axis=2) & np.isfinite(cov).all(axis=(2, 3))  # frame-major, markers in order
        if not ok.any():
            return False
        frames = _logged_frames(ok.sum(axis=1))
        lengths, centers = ok.sum(axis=1)[frames], pos[ok]
        half, quats = ellipsoid_columns(cov[ok])
        cols = rr.Ellipsoids3D.columns(centers=centers, half_sizes=half, quaternions=quats,
                                       colors=np.tile(method_rgb(meth), (len(centers), 1)).astype(np.uint8),
                                       fill_mode=[rr.components.FillMode.MajorWireframe] * len(centers))
        self._columns(f"world/uncertainty/{meth}", frames, cols.partition(lengths.tolist()))
        return True

    def _target(self, est: EstimateResult, truth: dict | None, n: int) -> None:
        """The four-point target: the true plate as a closed outline per frame, each target
        method's centre (points and path) and its α and z series beside the truth's."""
        import rerun as rr

        if est.target is None or not est.target_tracks:
            return
        corners = [f"{est.target.name}_{j}" for j in range(1, 5)]
        if truth is not None and all(c in truth for c in corners):
            frames = [k for k in range(n) if all(k < len(truth[c]) and np.all(np.isfinite(truth[c][k])) for c in corners)]
            strips = [np.array([truth[c][k] for c in [*corners, corners[0]]]) for k in frames]
            if frames:
                cols = rr.LineStrips3D.columns(strips=strips, colors=[TRUTH_RGB_VIEWER] * len(strips),
                                               radii=[PATH_RADIUS] * len(strips))
                self._columns("world/truth/plate", np.array(frames, dtype=np.int64), cols.partition([1] * len(frames)))
        for meth, tr in est.target_tracks.items():
            rgb = list(method_rgb(meth))
            pts = _batches([tr.position], len(tr.position))
            self._points(f"world/estimates/{meth}/points", pts, np.tile(rgb, (len(pts.points), 1)),
                         ["centre"] * len(pts.points), "3d", POINT_RADIUS, show_labels=False)
            self._paths(f"world/estimates/{meth}/path", [tr.position], rgb)
            self._scalars(f"metrics/target/alpha/{meth}", 1000.0 * tr.extra["alpha"], meth, rgb)  # mrad, mm: as the tables
            self._scalars(f"metrics/target/distance/{meth}", 1000.0 * tr.extra["distance"], meth, rgb)
        tg = est.target
        if tg.alpha is not None and tg.distance is not None:
            self._scalars("metrics/target/alpha/truth", 1000.0 * np.asarray(tg.alpha), "truth", TRUTH_RGB_VIEWER)
            self._scalars("metrics/target/distance/truth", 1000.0 * np.asarray(tg.distance), "truth", TRUTH_RGB_VIEWER)

    def abort(self) -> None:
        """Stop recording and remove the partial file (after the file sink has closed it, so that
        no late write recreates it)."""
        try:
            if self.rec is not None and not self.stalled:  # a stalled sink's disconnect never returns
                self.rec.disconnect()
        finally:
            self.tmp.unlink(missing_ok=True)
