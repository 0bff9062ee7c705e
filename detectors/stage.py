"""The detect stage: a clip folder (or a single video) → ``out/detections.csv`` and a
per-camera summary, with pixel errors against ``truth.csv`` when the clip has one."""

from __future__ import annotations

from array import array
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from detectors import check_detector, create_detector
from detectors.blob import BlobDetector, MarkerColor
from detectors.markers import resolve_marker_specs
from pipeline.core.camera import StereoRig
from pipeline.core.checks import (
    Check,
    check_view_sizes,
    colour_checks,
    rarely_found_checks,
    rig_for_frames,
    warn_failed,
)
from pipeline.core.clip import CLIP_INFO, DETECTION_WRITTEN, MARKERS_FILE, TIMESTAMPS, Clip, FootageInfo
from pipeline.core.detections import Detections, GroupDetections, GroupFlags, blob_flags, group_names, split_groups
from pipeline.core.errors import StereotrackError
from pipeline.core.frames import CameraReader, StereoFrameSource
from pipeline.core.io import write_csv_columns, write_json
from pipeline.core.outputs import Outputs
from pipeline.core.rig import Rig
from pipeline.core.settings import RunHooks, RunSettings

#: The detect stage's record beside detections.csv: frames, frame size, markers used, checks.
#: A clip folder (or a batch's input root) may name its markers here, in ``--markers`` syntax.
#: Whole frames sampled per camera for the colour-range checks.
CHECK_SAMPLES = 10
CAMERAS = ("left", "right")


@dataclass
class CameraSummary:
    camera: str
    frames: int
    detections: int
    misses: int | None = None  # visible in truth but not detected
    false: int | None = None  # detected while truth says the marker is hidden (occluded, out of frame, dropped)
    err_median: float | None = None
    err_p95: float | None = None
    err_max: float | None = None


@dataclass
class DetectResult:
    path: Path
    rows: DetectionTable  # every detection written, in compact columns; iterating gives the CSV's rows
    summaries: list[CameraSummary] = field(default_factory=list)
    learned: dict[str, str] = field(default_factory=dict)  # window-learned marker → the range chosen
    checks: list[Check] = field(default_factory=list)
    marker_colours: dict[str, list[int]] = field(default_factory=dict)  # for drawing, RGB
    observations: dict[str, np.ndarray] = field(default_factory=dict)  # marker → frames × [u1, v1, u2, v2]
    footage: FootageInfo | None = None  # what the estimate stage needs to know of the frames
    groups: dict[str, GroupDetections] = field(default_factory=dict)  # identical markers: per frame, per camera
    merged: dict[str, GroupFlags] = field(default_factory=dict)  # beside ``groups``: blobs of merged images

    def detections(self) -> Detections:
        """What the estimate stage takes of this result, in memory."""
        assert self.footage is not None  # the detect stage always says what it saw
        return Detections(self.observations, self.footage, self.groups, self.merged)


def markers_for_clip(clip: Clip, specs: list[str] | None, left_frame: Callable[[int], np.ndarray | None] | None = None,
                     learned: dict[str, str] | None = None,
                     force: bool = False) -> tuple[list[MarkerColor], dict[str, list[str]]]:
    """Marker colour ranges (from ``--markers`` specs, else ``markers.yaml``, else the clip's
    description of a rendered clip) and, for four-point targets whose points share one colour, the group name →
    its four point names. A ``NAME@x,y,w,h[@FRAME]`` spec learns its range from that window of
    the left camera's frame FRAME (default the first), read through ``left_frame``; the ranges
    chosen go into ``learned``; ``force`` keeps a learned range that selects far more than the
    marker (see :meth:`MarkerColor.learn`). ``specs`` are resolved already (see
    :func:`detectors.markers.resolve_marker_specs`)."""
    colors: list[MarkerColor] = []
    if specs:
        for spec in specs:
            win = MarkerColor.parse_window(spec)
            if win is None:
                colors.append(MarkerColor.parse(spec))
                continue
            frame = left_frame(win[2]) if left_frame is not None else None
            if frame is None:
                raise StereotrackError(f"marker {spec!r} learns its colour from left frame {win[2]}, which is missing",
                                       clip.path)
            mk = MarkerColor.learn(win[0], frame, win[1], f" (left frame {win[2]} of {clip.path})", force)
            colors.append(mk)
            if learned is not None:
                learned[mk.name] = mk.spec()
        names = [c.name for c in colors]
        for name in names:
            if names.count(name) > 1:
                given = [s for s, n in zip(specs, names, strict=True) if n == name]
                raise StereotrackError(f"marker name {name!r} is given twice ({', '.join(given)}): one name per marker, "
                                       "or two colours would merge into one track", clip.path)
        return colors, {}
    if not clip.markers:
        raise StereotrackError(f"no marker colours: give --markers NAME:HLO-HHI, NAME=#RRGGBB or NAME@x,y,w,h, "
                               f"or put them in {MARKERS_FILE} (no {CLIP_INFO} or scenario.yaml to take them from)",
                               clip.path)
    colors = []
    groups: dict[str, list[str]] = {}
    for info in clip.markers:
        if info.group is None:
            colors.append(MarkerColor.from_rgb(info.name, info.rgb))
        elif info.group not in groups:
            colors.append(MarkerColor.from_rgb(info.group, info.rgb))
            groups[info.group] = [m.name for m in clip.markers if m.group == info.group]
    return colors, groups


def detect_clip(clip: str | Path | Clip, settings: RunSettings | None = None, out_dir: str | Path | None = None,
                hooks: RunHooks | None = None, workers: int = 1) -> DetectResult:
    """Detect every marker in every frame of both cameras and write ``detections.csv`` and
    ``detect.json`` (frames, frame size, the marker ranges used, the colour checks).

    ``settings`` name the detector, the markers (default: the clip's own), the first search window,
    the calibration's units and the frame rate; ``hooks.frame(index, left, right)`` receives every
    decoded frame (``run`` records them as they go by, so a clip is decoded once and never held
    in memory), or with ``hooks.image`` what each camera's worker made of it; ``hooks.progress``
    the frames done. ``workers`` ≥ 2: each camera is decoded and detected in a process of its own
    when the detector :attr:`~detectors.base.Detector.forks` and ``hooks.frame`` does not want the
    images themselves (else in threads of this one; the detections are the same).

    Coordinates written are undistorted with the clip's calibration when it has one (real rigs
    have lens distortion; estimators need pinhole coordinates); a calibration for another image
    size is an error, or scaled with a warning when only the resolution differs.
    """
    settings, hooks = settings or RunSettings(), hooks or RunHooks()
    check_detector(settings.detector)
    clip_ = Clip.open(clip, settings.fps)
    source = StereoFrameSource(clip_.path, allow_unequal=settings.allow_unequal, fps=clip_.fps, cameras=clip_.cameras)
    out_dir = Outputs.of(clip_.folder, out_dir).folder
    rig: StereoRig | Rig | None = None
    checks: list[Check] = []
    if clip_.has_calibration:
        found = clip_.rig(settings.calib_units)
        if isinstance(found, Rig):
            check_view_sizes(found, source.sizes, clip_.folder / clip_.calibration_name)
            rig = found
        else:
            rig, size_check = rig_for_frames(found, source.size, clip_.path)
            checks += [size_check] if size_check else []
    learned: dict[str, str] = {}
    specs = resolve_marker_specs(clip_.path, list(settings.markers) if settings.markers else None)
    markers, groups = markers_for_clip(clip_, specs, lambda k: _left_frame(source, k), learned, settings.force_window)
    if clip_.shaded:  # lit objects: their centres are unmixed from the background (detectors.centroid)
        markers = [replace(m, shaded=True) for m in markers]
    identical = set(clip_.identical_groups()) & set(groups)
    targets = {g: names for g, names in groups.items() if g not in identical}
    finders = [create_detector(settings.detector, markers, targets, settings.roi, identical)
               for _ in range(len(source.readers))]
    scan = _scan(source, finders, rig, markers, {n for names in groups.values() for n in names} | set(groups),
                 hooks, forked=workers > 1 and all(type(f).forks for f in finders)
                 and (hooks.frame is None or hooks.image is not None))
    _check_footage_times(clip_, source, scan.counts)
    cols = scan.rows.columns()
    checks += colour_checks(scan.samples)
    checks += rarely_found_checks(cols, scan.frames, scan.rows.cameras, [m.name for m in markers if m.name not in groups])
    warn_failed(checks)
    record = {"detector": settings.detector, "markers": [m.spec() for m in markers], "learned": learned,
              "marker_colours": {m.name: list(m.display_rgb()) for m in markers},
              "centres": "unmixed" if clip_.shaded else "chroma"}
    return _write_detections(out_dir, clip_, source, scan, cols, checks, record)


def _check_footage_times(clip: Clip, source: StereoFrameSource, counts: list[int]) -> None:
    """Every frame each camera's footage holds has a time in ``timestamps.csv``, and every time of a
    video's is of a frame it holds: a video longer or shorter than its timestamps (frames lost in
    recording or copying) cannot be paired by time, so it is one error naming the file. A frame
    folder's file numbers say which frames are missing (a time without its file is a missed frame)."""
    if clip.timestamps is None or len(source.readers) < 2:
        return
    path = clip.folder / TIMESTAMPS
    for cam, reader, n in zip(clip.cameras, source.readers, counts, strict=True):
        held = np.ones(n, dtype=bool)
        held[[g for g in reader.gaps if g < n]] = False
        t = clip.timestamps[cam]
        listed = np.zeros(max(n, len(t)), dtype=bool)
        listed[: len(t)] = np.isfinite(t)
        if reader.files is None and (extra := np.flatnonzero(listed[n:])).size:  # a folder's numbers say which is missing
            raise StereotrackError(f"lists {cam} frame {n + int(extra[0])} but the {cam} footage has {n} frames "
                                   f"(0–{n - 1}): footage shorter than its timestamps cannot be paired by time "
                                   "(frames lost?)", path)
        if (untimed := np.flatnonzero(held & ~listed[:n])).size:
            raise StereotrackError(f"has no time for {cam} frame {int(untimed[0])} ({untimed.size} of the footage's "
                                   f"{n} frames have none): every frame needs a row", path)


class DetectionTable:
    """Detections as the scan finds them, in compact columns (a long clip has tens of thousands;
    as Python tuples each row weighs about 200 bytes, and the memory stays with the process)."""

    def __init__(self, cameras: tuple[str, ...] = CAMERAS) -> None:
        self.cameras = cameras
        self.frame, self.camera, self.marker = array("q"), array("b"), array("h")
        self.u, self.v, self.area, self.score = array("d"), array("d"), array("d"), array("d")
        self.names: list[str] = []
        self._index: dict[str, int] = {}

    def add(self, frame: int, camera: int, marker: str, u: float, v: float, area: float, score: float) -> None:
        if marker not in self._index:
            self._index[marker] = len(self.names)
            self.names.append(marker)
        self.frame.append(frame)
        self.camera.append(camera)
        self.marker.append(self._index[marker])
        for col, value in ((self.u, u), (self.v, v), (self.area, area), (self.score, score)):
            col.append(value)

    def __len__(self) -> int:
        return len(self.frame)

    def undistort(self, rig: StereoRig | Rig) -> None:
        """Each camera's pixel coordinates undistorted in place, all of them in one call (the same
        per-point iteration as one call per detection, without its overhead)."""
        cams = np.frombuffer(self.camera, dtype=np.int8)
        u, v = np.frombuffer(self.u, dtype=float), np.frombuffer(self.v, dtype=float)
        for c, cam in enumerate(rig.cameras):
            mine = cams == c
            if mine.any():
                u[mine], v[mine] = cam.undistort(np.column_stack([u[mine], v[mine]])).T

    def columns(self) -> dict[str, np.ndarray]:
        """The ``detections.csv`` columns as arrays (camera and marker names as strings)."""
        names = np.array(self.names, dtype=object)
        return {"frame": np.frombuffer(self.frame, dtype=np.int64).astype(float),
                "camera": np.array(self.cameras, dtype=object)[np.frombuffer(self.camera, dtype=np.int8)],
                "marker": names[np.frombuffer(self.marker, dtype=np.int16)],
                **{k: np.frombuffer(getattr(self, k), dtype=float) for k in ("u", "v", "area", "score")}}

    def table(self) -> list:
        """The rows of :meth:`__iter__` as columns, for :func:`~pipeline.core.io.write_csv_columns`."""
        return [np.frombuffer(self.frame, dtype=np.int64), [self.cameras[c] for c in self.camera],
                [self.names[m] for m in self.marker], *(np.frombuffer(getattr(self, k), dtype=float)
                                                         for k in ("u", "v", "area", "score"))]

    def __iter__(self) -> Iterator[tuple]:
        """The table's rows ``(frame, camera, marker, u, v, area, score)``, in the order found
        (``detections.csv``)."""
        for k, c, m, u, v, a, sc in zip(self.frame, self.camera, self.marker, self.u, self.v, self.area, self.score,
                                        strict=True):
            yield k, self.cameras[c], self.names[m], u, v, a, sc


@dataclass
class _Scanned:
    rows: DetectionTable
    samples: dict[tuple[str, str], list]
    frames: int
    cameras: int
    #: the frames each camera's footage held (decoded, or missing files of a frame folder)
    counts: list[int] = field(default_factory=list)


class _CameraScan:
    """One camera's work on each of its frames, run in its decode thread or process: the colour
    samples of the sampled frames, then the detector (reset on a missing frame); beside the
    detections, what ``image(camera, k, img)`` makes of the frame (None without it)."""

    def __init__(self, finder, markers: list[MarkerColor], cam: str, sample_at: set[int], unsampled: set[str],
                 camera: int = 0, image: Callable[[int, int, Any], Any] | None = None) -> None:
        self.finder, self.cam, self.sample_at, self.unsampled = finder, cam, sample_at, unsampled
        self.camera, self.image = camera, image
        self.sampler = BlobDetector(markers, max_per_marker=2)
        self.samples: dict[tuple[str, str], list] = {}
        self.k = 0

    def __call__(self, img: np.ndarray | None) -> tuple[list, Any]:
        k, self.k = self.k, self.k + 1
        made = self.image(self.camera, k, img) if self.image is not None else None
        if img is None:  # a missing frame file: no detection in this camera
            self.finder.reset()
            return [], made
        if k in self.sample_at:
            _sample_colours(self.sampler, img, self.cam, self.unsampled, self.samples)
        return self.finder.detect(img), made

    def handover(self) -> tuple[int, dict]:
        """What the scan reads after the last frame (frames seen, colour samples), when this camera
        ran in a process of its own (:meth:`StereoFrameSource.frames`)."""
        return self.k, self.samples

    def take(self, state: tuple[int, dict]) -> None:
        self.k, self.samples = state


def _scan(source: StereoFrameSource, finders: list, rig: StereoRig | Rig | None, markers: list[MarkerColor],
          unsampled: set[str], hooks: RunHooks, forked: bool = False) -> _Scanned:
    """Every frame through each camera's detector, with whole-frame colour samples from a few frames
    for the colour checks; coordinates undistorted at the end when there is a calibration. Each
    camera detects in its own decode thread (:meth:`StereoFrameSource.frames`), so the two cameras'
    detection overlaps; ``forked``: in a process of its own, side by side."""
    total = len(source)
    sample_at = set(np.linspace(0, max(total - 1, 0), min(CHECK_SAMPLES, max(total, 1))).astype(int).tolist())
    names = source.cameras if len(finders) > 1 else CAMERAS[:1]
    out = _Scanned(DetectionTable(tuple(names)), {}, 0, len(finders))
    cams = [_CameraScan(f, markers, names[c], sample_at, unsampled, c, hooks.image) for c, f in enumerate(finders)]
    for fr in source.frames(cams, forked=forked):
        results = [r if r is not None else ((), None) for r in fr.found]  # None: that camera's frames ended
        if hooks.frame is not None:
            hooks.frame(fr.index, *([made for _, made in results] if hooks.image is not None else fr.images))
        for c, (found, _) in enumerate(results):
            for d in found:
                out.rows.add(fr.index, c, d.marker, d.u, d.v, d.area, d.score)
        out.frames = fr.index + 1
        hooks.tick(out.frames, total)
    out.counts = [cs.k for cs in cams]
    if rig is not None:
        out.rows.undistort(rig)
    out.samples = {(m.name, cs.cam): cs.samples[m.name, cs.cam] for cs in cams for m in markers
                   if (m.name, cs.cam) in cs.samples}  # left's markers, then right's, in marker order
    return out


def _write_detections(out_dir: Path, clip: Clip, source: StereoFrameSource, scan: _Scanned,
                      cols: dict[str, np.ndarray], checks: list[Check], record: dict) -> DetectResult:
    """``detections.csv`` and ``detect.json`` (``cols``: the scan's rows as columns); the result the
    estimate stage takes in memory."""
    path = Outputs(out_dir).detections
    index, merged = blob_flags(cols, group_names(cols, clip.identical_groups(), clip.cameras, path))
    observations, groups, flags = split_groups({**cols, "merged": merged}, scan.frames, path, clip.identical_groups(),
                                               clip.cameras)
    write_csv_columns(path, DETECTION_WRITTEN, [*scan.rows.table(), index, merged])
    summaries = summarize(cols, clip, scan.frames, scan.cameras)
    cameras = [asdict(s) for s in summaries]
    write_json(Outputs(out_dir).detect_info, {
        "clip": str(clip.path), "frames": scan.frames, "frame_size": list(source.size), "stereo": source.stereo,
        **record, "checks": [c.as_dict() for c in checks], "cameras": cameras})
    return DetectResult(path, scan.rows, summaries, learned=record["learned"], checks=checks,
                        marker_colours=record["marker_colours"],
                        observations=observations, groups=groups, merged=flags,
                        footage=FootageInfo(scan.frames, tuple(source.size), checks, cameras))


def _left_frame(source: StereoFrameSource, k: int) -> np.ndarray | None:
    """Left frame ``k``, read by a reader of its own (the source is iterated afterwards)."""
    reader = CameraReader(source.readers[0].source, getattr(source.readers[0], "first", None))
    try:
        for i, img in enumerate(reader):
            if i == k:
                return img
        return None
    finally:
        reader.close()


def _sample_colours(sampler: BlobDetector, img: np.ndarray, cam: str, skip: set[str],
                    samples: dict[tuple[str, str], list]) -> None:
    """Whole-frame mask coverage and the two largest blobs of each marker's colour (colour checks),
    measured on the frame at half resolution (areas scaled back to full-resolution pixels): the
    check asks whether a range selects far more than a marker, not where the marker is."""
    small = cv2.resize(img, (img.shape[1] // 2, img.shape[0] // 2), interpolation=cv2.INTER_AREA)
    scale = (img.shape[0] * img.shape[1]) / (small.shape[0] * small.shape[1])
    hsv = cv2.cvtColor(small, cv2.COLOR_BGR2HSV)
    for mk in sampler.markers:
        if mk.name in skip:
            continue
        mask = mk.mask(hsv)
        mask_px = int(cv2.countNonZero(mask)) * scale
        _, stats, blobs = sampler.blobs(mask)  # the blobs the detector would find: their areas, no centroids
        areas = [*sorted((float(b[1][4]) * scale for b in blobs), reverse=True), 0.0, 0.0]
        one = float(stats[1:, cv2.CC_STAT_AREA].max()) * scale / mask_px if len(stats) > 1 and mask_px else 0.0
        samples.setdefault((mk.name, cam), []).append((mask_px / (img.shape[0] * img.shape[1]), mask_px, areas[0],
                                                      areas[1], one))


def summarize(cols: dict[str, np.ndarray], clip: Clip, n_frames: int, n_cams: int) -> list[CameraSummary]:
    """Frames, detections, misses and pixel errors against truth (when ``truth.csv`` exists), from
    the detection columns (the ``detections.csv`` schema)."""
    truth = clip.truth_table()
    identical = clip.identical_groups()
    if truth is not None and identical:  # identical markers are scored by identity, after estimation
        members = [n for names in identical.values() for n in names]
        truth = {k: v[~np.isin(truth["marker"], members)] for k, v in truth.items()}
        cols = {k: v[~np.isin(cols["marker"], list(identical))] for k, v in cols.items()}
    out = []
    grid = _footage_to_grid(clip) if truth is not None else None
    for c in range(n_cams):
        cam = clip.cameras[c] if n_cams > 1 else CAMERAS[0]
        mine = {k: v[cols["camera"] == cam] for k, v in cols.items()}
        s = CameraSummary(cam, n_frames, len(mine["frame"]))
        if truth is not None:
            _against_truth(s, mine, truth, grid[cam] if grid is not None else None)
        out.append(s)
    return out


def _against_truth(s: CameraSummary, mine: dict[str, np.ndarray], truth: dict[str, np.ndarray],
                   place: np.ndarray | None) -> None:
    """One camera's misses, false detections and pixel errors: each truth row (a grid frame and a
    marker; ``place`` maps footage frames to grid frames) against the last detection of that
    marker in that frame, as arrays (a long clip's truth is tens of thousands of rows)."""
    cam = s.camera
    names = sorted(set(truth["marker"].tolist()) | set(mine["marker"].tolist()))
    index = {n: i for i, n in enumerate(names)}
    frames = mine["frame"].astype(np.int64)
    if place is not None and len(frames):
        frames = np.asarray(place, dtype=np.int64)[frames]
    keys = frames * len(names) + np.array([index[n] for n in mine["marker"]], dtype=np.int64)
    tkeys = truth["frame"].astype(np.int64) * len(names) + np.array([index[n] for n in truth["marker"]], dtype=np.int64)
    table = np.full(max(int(keys.max(initial=-1)), int(tkeys.max(initial=-1))) + 1, -1, dtype=np.int64)
    np.maximum.at(table, keys, np.arange(len(keys)))  # the last detection of a (frame, marker) wins
    hit = table[tkeys] if len(tkeys) else np.zeros(0, dtype=np.int64)
    vis = truth[f"visible_{cam}"].astype(bool)
    found = hit >= 0
    s.misses, s.false = int(np.sum(vis & ~found)), int(np.sum(~vis & found))
    ok = vis & found
    if ok.any():
        # detections are undistorted: compare with the pinhole truth where the clip has it
        us, vs = (truth.get(f"{a}_{cam}_pinhole", truth[f"{a}_{cam}"]) for a in ("u", "v"))
        e = np.hypot(mine["u"][hit[ok]] - us[ok], mine["v"][hit[ok]] - vs[ok])
        s.err_median, s.err_p95, s.err_max = float(np.median(e)), float(np.percentile(e, 95)), float(e.max())


def _footage_to_grid(clip: Clip) -> dict[str, np.ndarray] | None:
    """Per camera, each footage frame's frame on the clip's grid (a video that dropped frames is
    shorter than the truth), from timestamps.csv; None without one."""
    from pipeline.core.timestamps import nominal_frames

    if clip.timestamps is None:
        return None
    return {cam: nominal_frames(t, clip.fps) for cam, t in clip.timestamps.items()}
