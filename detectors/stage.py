"""The detect stage: a clip folder (or a single video) → ``out/detections.csv`` (SPEC §3) and a
per-camera summary, with pixel errors against ``truth.csv`` when the clip has one."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from scipy.optimize import linear_sum_assignment

from detectors.blob import BlobDetector, Detection, MarkerColor
from detectors.frames import StereoFrameSource
from detectors.meanshift import MeanShiftTracker
from pipeline.camera import StereoRig, load_calibration
from pipeline.errors import StereotrackError
from pipeline.io import read_csv, write_csv

DETECTION_COLUMNS = ["frame", "camera", "marker", "u", "v", "area", "score"]
CAMERAS = ("left", "right")
DetectorName = Literal["blob", "meanshift", "camshift"]


@dataclass
class CameraSummary:
    camera: str
    frames: int
    detections: int
    misses: int | None = None  # visible in truth but not detected
    false: int | None = None  # detected while truth says not visible
    err_median: float | None = None
    err_p95: float | None = None
    err_max: float | None = None


@dataclass
class DetectResult:
    path: Path
    rows: list[tuple]
    summaries: list[CameraSummary] = field(default_factory=list)


def markers_for_clip(clip: Path, specs: list[str] | None) -> tuple[list[MarkerColor], dict[str, list[str]]]:
    """Marker colour ranges (from ``--markers`` specs, else the clip's scenario.yaml) and, for
    four-point targets whose points share one colour, the group name → its four point names."""
    if specs:
        return [MarkerColor.parse(s) for s in specs], {}
    scen_path = clip / "scenario.yaml" if clip.is_dir() else None
    if scen_path is None or not scen_path.is_file():
        raise StereotrackError("no scenario.yaml to take marker colours from: give --markers NAME:HLO-HHI or NAME=#RRGGBB", clip)
    from renderers.scenario import load_scenario

    scen = load_scenario(scen_path)
    colors: list[MarkerColor] = []
    groups: dict[str, list[str]] = {}
    for obj in scen.objects:
        names, cols = obj.marker_names(), obj.marker_colors()
        if obj.is_target and len(set(cols)) == 1:
            colors.append(MarkerColor.from_rgb(obj.name, cols[0]))
            groups[obj.name] = names
        else:
            colors += [MarkerColor.from_rgb(n, c) for n, c in zip(names, cols, strict=True)]
    return colors, groups


def label_four_points(points: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """Order four image points as SPEC §4.8 numbers them: 2 and 4 on the rotation axis (the pair
    2R apart, not foreshortened, i.e. the longer diagonal), 2 to the right; 1 above the axis.
    With the previous frame's labelled points, keep labels by optimal assignment instead, so
    labels never swap while the target moves."""
    if previous is not None and np.all(np.isfinite(previous)):
        cost = np.linalg.norm(points[:, None, :] - previous[None, :, :], axis=2)
        rows, cols = linear_sum_assignment(cost)
        out = np.empty_like(points)
        out[cols] = points[rows]
        return out
    d = np.linalg.norm(points[:, None] - points[None], axis=2)
    pairs = [((0, 1), (2, 3)), ((0, 2), (1, 3)), ((0, 3), (1, 2))]
    (a, b), (c, e) = max(pairs, key=lambda pr: max(d[pr[0]], d[pr[1]]))
    axis, other = ((a, b), (c, e)) if d[a, b] >= d[c, e] else ((c, e), (a, b))
    p2, p4 = sorted(axis, key=lambda i: -points[i, 0])
    direction = points[p2] - points[p4]
    normal = np.array([direction[1], -direction[0]])  # points "up" (−y) for a rightward axis
    p1, p3 = sorted(other, key=lambda i: -float((points[i] - points[p4]) @ normal))
    return points[[p1, p2, p3, p4]]


def detect_clip(
    clip: str | Path,
    detector: DetectorName = "blob",
    marker_specs: list[str] | None = None,
    roi: tuple[int, int, int, int] | None = None,
    allow_unequal: bool = False,
    out_dir: str | Path | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> DetectResult:
    """Detect every marker in every frame of both cameras and write ``detections.csv``.

    Coordinates written are undistorted with the clip's calibration when it has one (real rigs
    have lens distortion; estimators need pinhole coordinates).
    """
    clip = Path(clip)
    source = StereoFrameSource(clip, allow_unequal=allow_unequal)
    base = clip if clip.is_dir() else clip.parent
    out_dir = Path(out_dir) if out_dir else base / "out"
    rig: StereoRig | None = None
    if clip.is_dir() and any((clip / n).is_file() for n in ("calib.yaml", "calib.yml", "intrinsics.yml")):
        rig = load_calibration(clip)
    markers, groups = markers_for_clip(clip, marker_specs)
    n_cams = 2 if source.stereo else 1
    if detector == "blob":
        blob = BlobDetector(markers, max_per_marker=4)
    elif detector in ("meanshift", "camshift"):
        if groups:
            raise StereotrackError("meanshift/camshift track one point per colour: use blob for a one-colour target")
        trackers = [[MeanShiftTracker(m, detector, roi) for m in markers] for _ in range(n_cams)]
    else:
        raise StereotrackError(f"unknown detector {detector!r} (blob, meanshift, camshift)")
    rows: list[tuple] = []
    previous: dict[tuple[int, str], np.ndarray] = {}
    windows: list[dict[str, tuple[int, int, int, int]]] = [{}, {}]  # blob search windows per camera
    grouped = {n for names in groups.values() for n in names}
    total = len(source)
    for fr in source:
        images = [fr.left] if fr.right is None else [fr.left, fr.right]
        for c, img in enumerate(images):
            if detector == "blob":
                dets = _best_per_marker(blob.detect(img, rois=windows[c]), groups, previous, c)
                windows[c] = {d.marker: _window(d, img.shape) for d in dets if d.marker not in grouped}
            else:
                dets = [d for t in trackers[c] if (d := t.update(img)) is not None]
            for d in dets:
                u, v = d.u, d.v
                if rig is not None:
                    u, v = rig.cameras[c].undistort(np.array([[u, v]]))[0]
                rows.append((fr.index, CAMERAS[c], d.marker, u, v, d.area, d.score))
        if progress is not None:
            progress(fr.index + 1, total)
    path = out_dir / "detections.csv"
    write_csv(path, DETECTION_COLUMNS, rows)
    result = DetectResult(path, rows)
    result.summaries = summarize(rows, clip, fr.index + 1 if total else 0, n_cams)
    return result


def _window(d: Detection, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    """Search window for the next frame: the blob's size plus room for fast motion."""
    r = max(np.sqrt(d.area / np.pi), 2.0)
    half = int(3 * r + 24)
    x0, y0 = max(int(d.u) - half, 0), max(int(d.v) - half, 0)
    return x0, y0, min(2 * half, shape[1] - x0), min(2 * half, shape[0] - y0)


def _best_per_marker(dets: list[Detection], groups: dict[str, list[str]], previous: dict, cam: int) -> list[Detection]:
    out: list[Detection] = []
    by: dict[str, list[Detection]] = {}
    for d in dets:
        by.setdefault(d.marker, []).append(d)
    for name, ds in by.items():
        if name in groups:
            if len(ds) < 4:
                continue  # fewer than four points: the target is skipped this frame
            ds = sorted(ds, key=lambda d: -d.area)[:4]
            pts = np.array([[d.u, d.v] for d in ds])
            labelled = label_four_points(pts, previous.get((cam, name)))
            previous[(cam, name)] = labelled
            lookup = {(round(d.u, 6), round(d.v, 6)): d for d in ds}
            for point_name, p in zip(groups[name], labelled, strict=True):
                d = lookup[(round(p[0], 6), round(p[1], 6))]
                out.append(Detection(point_name, d.u, d.v, d.area, d.score))
        else:
            out.append(ds[0])
    return out


def summarize(rows: list[tuple], clip: Path, n_frames: int, n_cams: int) -> list[CameraSummary]:
    """Frames, detections, misses and pixel errors against truth (when ``truth.csv`` exists)."""
    truth_path = clip / "truth.csv" if clip.is_dir() else None
    truth = read_csv(truth_path) if truth_path is not None and truth_path.is_file() else None
    out = []
    for c in range(n_cams):
        cam = CAMERAS[c]
        mine = [r for r in rows if r[1] == cam]
        s = CameraSummary(cam, n_frames, len(mine))
        if truth is not None:
            det = {(int(r[0]), r[2]): (r[3], r[4]) for r in mine}
            errs, misses, false = [], 0, 0
            for k, name, u, v, vis in zip(truth["frame"], truth["marker"], truth[f"u_{cam}"], truth[f"v_{cam}"],
                                          truth[f"visible_{cam}"], strict=True):
                key = (int(k), name)
                if vis and key in det:
                    errs.append(np.hypot(det[key][0] - u, det[key][1] - v))
                elif vis:
                    misses += 1
                elif key in det:
                    false += 1
            s.misses, s.false = misses, false
            if errs:
                e = np.array(errs)
                s.err_median, s.err_p95, s.err_max = float(np.median(e)), float(np.percentile(e, 95)), float(e.max())
        out.append(s)
    return out


def load_detections(path: str | Path, n_frames: int | None = None) -> dict[str, np.ndarray]:
    """``detections.csv`` → per marker an array frames × 4 ``[u1, v1, u2, v2]`` (NaN = missed),
    keeping the highest-scoring detection per frame, camera and marker."""
    cols = read_csv(path, DETECTION_COLUMNS)
    if len(cols["frame"]) == 0:
        return {}
    frames = cols["frame"]
    if not np.all(np.isfinite(frames)):
        raise StereotrackError("non-numeric frame index", path)
    n = max(int(frames.max()) + 1, n_frames or 0)
    out: dict[str, np.ndarray] = {}
    best: dict[tuple[str, int, int], float] = {}
    for k, cam, name, u, v, score in zip(frames.astype(int), cols["camera"], cols["marker"], cols["u"], cols["v"],
                                          cols["score"], strict=True):
        c = {"left": 0, "right": 1}.get(str(cam))
        if c is None:
            raise StereotrackError(f"unknown camera {cam!r} (expected left/right)", path)
        if not (np.isfinite(u) and np.isfinite(v)):
            continue  # a NaN observation is a miss
        arr = out.setdefault(str(name), np.full((n, 4), np.nan))
        key = (str(name), int(k), c)
        if key in best and best[key] >= score:
            continue
        best[key] = score
        arr[k, 2 * c : 2 * c + 2] = (u, v)
    return out
