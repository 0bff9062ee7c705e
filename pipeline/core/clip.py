"""The clip folder, read in one place: which files a clip has and what they mean, and
the schemas of every table a clip or its ``out/`` folder holds (Kubric's one folder per scene,
with its settings written beside it).

A clip folder holds ``left``/``right`` videos (or folders of numbered frames) and a calibration;
a rendered clip adds ``clip.json`` (fps, markers and their colours, the four-point target's
description — written by the renderer from its scenario), ``scenario.yaml``, ``truth.csv`` and
``target_truth.csv``. :class:`Clip` loads each piece once, when first asked; every stage takes a
``Clip`` (or a path, opened here) so that nothing downstream needs to know how the clip was made.
Frames themselves are decoded by :mod:`pipeline.core.frames`.
"""

from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from pipeline.core.calibration import CALIB_NAMES, EXTRINSICS_NAMES, INTRINSICS_NAMES, has_calibration, load_calibration
from pipeline.core.camera import StereoRig
from pipeline.core.checks import Check
from pipeline.core.errors import ClipError, StereotrackError
from pipeline.core.frames import CameraReader, StereoFrameSource, find_camera_source
from pipeline.core.io import check_frame_column, read_csv, read_json_mapping
from pipeline.core.outputs import Outputs
from pipeline.core.rig import Rig
from pipeline.core.rigfiles import RIG_NAMES, find_rig, load_rig
from pipeline.core.schemas import (  # noqa: F401  (the clip's tables, named here for every reader)
    DETECTION_COLUMNS,
    DETECTION_WRITTEN,
    DETECTIONS,
    ESTIMATE_COLUMNS,
    ESTIMATES,
    SCHEMAS,
    STEREO,
    TARGET_COLUMNS,
    TARGET_ESTIMATES,
    TARGET_TRUTH,
    TARGET_TRUTH_COLUMNS,
    TIMESTAMP_COLUMNS,
    TIMESTAMPS,
    TIMESTAMPS_SCHEMA,
    TRUTH,
    TRUTH_COLUMNS,
    TRUTH_EXTRA_COLUMNS,
    truth_columns,
    truth_extra_columns,
)
from pipeline.core.timestamps import read_timestamps

CLIP_INFO = "clip.json"
MARKERS_FILE = "markers.yaml"
CLIP_SETTINGS = "clip.yaml"

class ClipSettings(BaseModel):
    """``clip.yaml`` in a clip folder: what the footage cannot say about itself."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)
    fps: float | None = Field(None, gt=0)
    """frames per second of both cameras (frame folders have no rate of their own; `--fps` wins)"""


@dataclass(frozen=True)
class MarkerInfo:
    """A marker a rendered clip shows: its name, colour (RGB) and, for the points of a four-point
    target that share one colour, the target it belongs to."""

    name: str
    rgb: tuple[int, int, int]
    group: str | None = None


@dataclass
class ClipTruth:
    """Per-marker truth positions (frames × 3) and the truth's frame count."""

    positions: dict[str, np.ndarray]
    n_frames: int



@dataclass
class TargetInfo:
    """A four-point target in a clip: its name, radius and (rendered clips) truth and dynamics."""

    name: str
    radius: float
    config: dict
    alpha: np.ndarray | None = None
    distance: np.ndarray | None = None



class Clip:
    """One clip folder (or a single stereo video file), each piece loaded once when first asked."""

    def __init__(self, path: str | Path, fps: float | None = None) -> None:
        self.path = Path(path)
        self.folder = self.path if self.path.is_dir() else self.path.parent
        if fps is not None and not (np.isfinite(fps) and fps > 0):
            raise StereotrackError(f"--fps must be a positive number of frames per second, not {fps:g}")
        self.given_fps = fps  # --fps: wins over everything the clip says
        self._rigs: dict[str | None, StereoRig | Rig] = {}
        self._file_rigs: dict[str | None, Rig] = {}
        self._truth: dict[int | None, ClipTruth | None] = {}

    @classmethod
    def open(cls, clip: str | Path | Clip, fps: float | None = None) -> Clip:
        """A :class:`Clip` for a path (a Clip is returned as it is, unless ``fps`` changes it)."""
        if isinstance(clip, Clip) and (fps is None or fps == clip.given_fps):
            return clip
        return cls(clip.path if isinstance(clip, Clip) else clip, fps)

    def __repr__(self) -> str:
        return f"Clip({str(self.path)!r})"

    # -- what the clip is ----------------------------------------------------------------------
    @cached_property
    def info(self) -> dict[str, Any]:
        """``clip.json`` (rendered clips), else ``{}`` (real footage; a clip rendered before
        clip.json existed is re-rendered, or given its markers like real footage)."""
        path = self.folder / CLIP_INFO
        if path.is_file():
            info = read_json_mapping(path, "clip description")
            try:
                _ = [(str(m["name"]), tuple(int(c) for c in m["rgb"])) for m in info.get("markers", [])]
                float(info.get("fps", 30.0))
            except (KeyError, TypeError, ValueError):
                raise ClipError("unreadable clip description (markers need 'name' and 'rgb'; fps a number)", path) from None
            return info
        return {}

    @property
    def shaded(self) -> bool:
        """Whether the clip was rendered with lit shading (its markers' limbs darker than their
        range's floor), which chooses how the detector finds a blob's centre. Real footage is not:
        there the unmixed centre is unverified (no truth) and on ``ball2.mp4`` it moved a fifth of the
        detections, by up to 1.6 px, toward the hand holding the ball."""
        return self.info.get("shading", "flat") == "lit"

    @property
    def markers(self) -> list[MarkerInfo]:
        """The markers a rendered clip shows (empty for real footage)."""
        return [MarkerInfo(m["name"], tuple(m["rgb"]), m.get("group")) for m in self.info.get("markers", [])]

    def identical_groups(self) -> dict[str, list[str]]:
        """Groups of identical markers (what the detector sees → each member's own name): the markers'
        groups other than the four-point target's, whose points are labelled by geometry instead."""
        target = (self.info.get("target") or {}).get("name")
        out: dict[str, list[str]] = {}
        for m in self.markers:
            if m.group is not None and m.group != target:
                out.setdefault(m.group, []).append(m.name)
        return out

    def group_truth(self, n_frames: int | None = None) -> dict[str, dict[str, np.ndarray]]:
        """Each group of identical markers → its members' true positions, NaN in the frames a member
        is in view of neither camera (``truth.csv``'s visibility): what a group's tracks are matched
        to and scored against. Empty for real footage or a clip without groups."""
        groups, truth = self.identical_groups(), self.truth(n_frames)
        if not groups or truth is None:
            return {}
        table = self.truth_table()
        out: dict[str, dict[str, np.ndarray]] = {}
        for g, names in groups.items():
            out[g] = {}
            for m in names:
                if m not in truth.positions:
                    continue
                P = truth.positions[m].copy()
                if table is not None and f"visible_{self.cameras[0]}" in table:
                    P[~_seen(table, m, len(P), self.cameras)] = np.nan
                out[g][m] = P
        return out

    @cached_property
    def settings(self) -> ClipSettings:
        """``clip.yaml``: the user's settings for this clip (today its frame rate), or defaults."""
        path = self.folder / CLIP_SETTINGS
        if not (self.path.is_dir() and path.is_file()):
            return ClipSettings()
        from pydantic import ValidationError

        from pipeline.core.io import read_yaml_mapping

        try:
            return ClipSettings.model_validate(read_yaml_mapping(path))
        except ValidationError as exc:
            err = exc.errors()[0]
            raise StereotrackError(f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}", path) from None

    @property
    def fps(self) -> float:
        """Frame rate (see :attr:`fps_source` for where it came from)."""
        return self._frame_rate[0]

    @property
    def fps_source(self) -> str:
        """Where :attr:`fps` came from: ``--fps``, ``clip.yaml``, ``clip.json``, ``timestamps.csv``,
        ``video header`` or ``default``."""
        return self._frame_rate[1]

    @cached_property
    def _frame_rate(self) -> tuple[float, str]:
        """``--fps``, else clip.yaml's ``fps``, else clip.json's (rendered clips), else the left
        camera's median frame period in timestamps.csv, else the left video's header, else 30
        (with a warning: a frame folder has no rate of its own)."""
        if self.given_fps is not None:
            return self._checked_rate(float(self.given_fps), "--fps"), "--fps"
        if self.settings.fps is not None:
            return self._checked_rate(float(self.settings.fps), f"{CLIP_SETTINGS}'s fps"), CLIP_SETTINGS
        if "fps" in self.info:
            return float(self.info["fps"]), CLIP_INFO
        stamped = self._timestamps_rate()
        if stamped is not None:
            return stamped, TIMESTAMPS
        try:
            reader = CameraReader(self.camera_source(self.cameras[0]) if self.path.is_dir() else self.path)
            reader.close()
        except StereotrackError:
            reader = None
        if reader is not None and reader.fps:
            return float(reader.fps), "video header"
        warnings.warn(f"{self.path}: no frame rate given (frame folders have none): assuming 30 fps; "
                      f"give --fps or `fps:` in {CLIP_SETTINGS}", stacklevel=3)  # past functools' cached_property
        return 30.0, "default"

    def _checked_rate(self, fps: float, source: str) -> float:
        """``fps`` as given, with a warning naming both when the clip's own frame times
        (timestamps.csv) or its video header say another rate (over 5 % apart)."""
        stamped = self._timestamps_rate()
        header = None
        if stamped is None and self.path.is_dir():
            try:
                reader = CameraReader(self.camera_source(self.cameras[0]))
                reader.close()
                header = reader.fps or None
            except StereotrackError:
                header = None
        for rate, what in ((stamped, TIMESTAMPS + "'s frame times"), (header, "the video header")):
            if rate and abs(fps / rate - 1) > 0.05:
                warnings.warn(f"{self.path}: {source} {fps:g} contradicts {what} ({rate:.4g} fps); using {fps:g} "
                              "(the frame grid, truth and time offsets follow it)", stacklevel=4)
        return fps

    @cached_property
    def timestamps(self) -> dict[str, np.ndarray] | None:
        """``timestamps.csv`` (per camera: footage frame → time, NaN where absent), read once; None
        without one."""
        path = self.folder / TIMESTAMPS
        if not (self.path.is_dir() and path.is_file()):
            return None

        return read_timestamps(path, self.cameras)

    def _timestamps_rate(self) -> float | None:
        """1 / the median period between consecutive left frames in timestamps.csv, if any."""
        if self.timestamps is None:
            return None
        t = self.timestamps[self.cameras[0]]
        frames = np.flatnonzero(np.isfinite(t))
        if len(frames) < 2:
            return None
        period = float(np.median(np.diff(t[frames]) / np.diff(frames)))
        return 1.0 / period if period > 0 else None

    def camera_source(self, name: str) -> Path:
        """``<name>.<video ext>`` or a ``<name>/`` folder of frames inside the clip folder."""
        return find_camera_source(self.folder, name)

    # -- calibration and truth -----------------------------------------------------------------
    @property
    def has_calibration(self) -> bool:
        return has_calibration(self.path) or (self.path.is_dir() and find_rig(self.folder) is not None)

    @property
    def calibration_name(self) -> str:
        """The calibration's file name, for messages."""
        for name in (*CALIB_NAMES, *EXTRINSICS_NAMES):
            if (self.folder / name).is_file():
                return name
        found = find_rig(self.folder) if self.path.is_dir() else None
        return found.name if found is not None else "the calibration"

    @cached_property
    def _rig_file(self) -> Path | None:
        """An N-camera rig file (rig.json, calib.toml, *.qca.txt, …) when the clip has no stereo
        calib.yaml and its footage is not left/right."""
        if not self.path.is_dir() or has_calibration(self.path):
            return None
        return find_rig(self.folder)

    def _file_rig(self, units: str | None) -> Rig:
        """The N-camera rig file as it reads (world: its own frame), read once per unit override."""
        if units not in self._file_rigs:
            assert self._rig_file is not None
            self._file_rigs[units] = load_rig(self._rig_file, units)
        return self._file_rigs[units]

    @cached_property
    def cameras(self) -> tuple[str, ...]:
        """The clip's camera names, its footage's file names: ``left``, ``right`` for a stereo clip;
        an N-camera clip's from its clip.json (rendered) or its rig file (``cam0``… or the names
        the file gives). A rig file of two cameras with ``left``/``right`` footage is a stereo clip."""
        named = self.info.get("cameras")
        if isinstance(named, list) and len(named) >= 2 and all(isinstance(n, str) for n in named):
            return tuple(named)
        if self._rig_file is not None:
            names = self._file_rig(None).names
            if not (len(names) == 2 and all(_has_source(self.folder, n) for n in STEREO)):
                return names
        return STEREO

    @property
    def stereo(self) -> bool:
        """Whether this is a two-camera clip with left/right footage (every method applies)."""
        return self.cameras == STEREO

    def rig(self, units: str | None = None) -> StereoRig | Rig:
        """The calibration (loaded once per unit override): a :class:`StereoRig` for a stereo
        clip, else the :class:`Rig` of its cameras in its first camera's frame."""
        if units not in self._rigs:
            if self._rig_file is None:
                self._rigs[units] = load_calibration(self.path, units)
            else:
                rig = self._file_rig(units)
                self._rigs[units] = rig.stereo(0, 1) if self.stereo else rig.in_frame_of(0)
        return self._rigs[units]

    def truth_table(self) -> dict[str, np.ndarray] | None:
        """``truth.csv`` as columns (with the projected pixels and visibility), or None. Read on
        each call, not kept: the detect stage's summary needs it once, and a long clip's table is
        megabytes (:meth:`truth` keeps the positions the later stages use)."""
        path = self.folder / "truth.csv"
        return read_csv(path, truth_columns(self.cameras)) if self.path.is_dir() and path.is_file() else None

    def truth(self, n_frames: int | None = None) -> ClipTruth | None:
        """``truth.csv`` (loaded once per frame count), or None for real footage."""
        if n_frames not in self._truth:
            self._truth[n_frames] = load_truth(self.folder, n_frames) if self.path.is_dir() else None
        return self._truth[n_frames]


@dataclass
class FootageInfo:
    """What the detect stage saw of the footage (``detect.json``), or the footage's headers."""

    frames: int | None
    frame_size: tuple[int, int] | None
    checks: list[Check]
    #: per camera: frames, detections, misses, false detections while hidden, pixel errors (truth only)
    cameras: list[dict] = field(default_factory=list)


def footage_info(clip: Path, out_dir: Path) -> FootageInfo:
    """Frame count and size of the clip, from ``detect.json`` when the detect stage wrote one,
    else from the footage itself (opened, not decoded), else unknown."""
    info = Outputs(out_dir).detect_info
    if info.is_file():
        try:
            d = json.loads(info.read_text())
            checks = [Check(**c) for c in d.get("checks", [])]
            w, h = d["frame_size"]
            return FootageInfo(int(d["frames"]), (int(w), int(h)), checks, list(d.get("cameras", [])))
        except (ValueError, KeyError, TypeError) as exc:
            raise StereotrackError(f"unreadable detect record ({exc}): rerun `stereotrack detect`", info) from None
    try:
        src = StereoFrameSource(clip, allow_unequal=True, prefetch=False)
    except StereotrackError:
        return FootageInfo(None, None, [])
    for r in src.readers:
        r.close()
    return FootageInfo(len(src), src.size, [])


#: Files of a clip folder that a run reads besides the footage (each only where present).
INPUT_FILES = (*CALIB_NAMES, *INTRINSICS_NAMES, *EXTRINSICS_NAMES, *RIG_NAMES, MARKERS_FILE, CLIP_SETTINGS, CLIP_INFO,
               "scenario.yaml", TIMESTAMPS, "truth.csv", "target_truth.csv")


def input_files(clip: str | Path) -> dict[str, Path]:
    """Every file a run of ``clip`` reads, by its name relative to the clip folder: both cameras'
    videos or frame files, the calibration, ``markers.yaml``, ``clip.json``, timestamps and truth
    (what a batch's manifest records, so that a changed input makes the clip be redone)."""
    clip = Path(clip)
    if clip.is_file():  # a single video
        return {clip.name: clip}
    found: dict[str, Path] = {}
    for cam in Clip(clip).cameras:
        try:
            src = find_camera_source(clip, cam)
        except ClipError:
            continue
        files = sorted(p for p in src.rglob("*") if p.is_file() and not p.name.startswith(".")) if src.is_dir() else [src]
        found.update({str(p.relative_to(clip)): p for p in files})
    found.update({n: clip / n for n in INPUT_FILES if (clip / n).is_file()})
    return found


def read_positions(path: Path, n_frames: int | None = None) -> tuple[dict[str, np.ndarray], int]:
    """A long-format table (``frame, marker, x, y, z``: truth.csv, estimates/*.csv) → marker →
    positions (frames × 3, NaN where absent), and the frame count. A row whose frame lies
    outside ``0 .. n_frames − 1`` is an error naming the line."""
    cols = read_csv(path, ["frame", "marker", "x", "y", "z"], numeric=["x", "y", "z"], finite=["frame"])
    check_frame_column(cols["frame"], n_frames, path)
    return positions_from_columns(cols)


def positions_from_columns(cols: dict[str, np.ndarray]) -> tuple[dict[str, np.ndarray], int]:
    """Columns of a long-format table (checked by the caller) → marker → positions, frame count."""
    frames = cols["frame"]
    n = int(np.nanmax(frames)) + 1 if len(frames) else 0
    pos: dict[str, np.ndarray] = {}
    for k, name, x, y, z in zip(cols["frame"].astype(int), cols["marker"], cols["x"], cols["y"], cols["z"], strict=True):
        pos.setdefault(str(name), np.full((n, 3), np.nan))[k] = (x, y, z)
    return pos, n



def load_truth(clip: str | Path, n_frames: int | None = None) -> ClipTruth | None:
    """``truth.csv`` → per-marker positions, or None for real footage. With the clip's frame
    count: rows past the clip are an error, a truth shorter than the clip a warning (the
    frames without truth are not scored)."""
    path = Path(clip) / "truth.csv"
    if not path.is_file():
        return None
    truth = ClipTruth(*read_positions(path, n_frames))
    if n_frames is not None and truth.n_frames < n_frames:
        warnings.warn(f"{path}: truth covers {truth.n_frames} of the clip's {n_frames} frames; "
                      f"the last {n_frames - truth.n_frames} are not scored", stacklevel=2)
    return truth



def find_target(clip: Clip, target_radius: float | None, obs: dict[str, np.ndarray]) -> TargetInfo | None:
    """The clip's four-point target: from its description (radius and the known dynamics the
    Kalman–Bucy filter assumes) or, for real footage, detections named NAME_1..NAME_4 plus
    ``target_radius``."""
    info = None
    desc = clip.info.get("target")
    if desc:
        info = TargetInfo(desc["name"], target_radius or float(desc["radius"]), dict(desc.get("config", {})))
    if info is None:
        names = {k.rsplit("_", 1)[0] for k in obs if k.rsplit("_", 1)[-1] in "1234" and "_" in k}
        full = [n for n in names if all(f"{n}_{j}" in obs for j in range(1, 5))]
        if not full:
            return None
        if target_radius is None:
            raise StereotrackError(f"four-point target '{full[0]}' found: give its radius (--target-radius)", clip.folder)
        info = TargetInfo(full[0], target_radius, {})
    path = clip.folder / "target_truth.csv"
    if path.is_file():
        tt = read_csv(path, ["frame", "alpha", "distance"])
        info.alpha, info.distance = tt["alpha"], tt["distance"]
    return info


def _seen(table: dict[str, np.ndarray], marker: str, n: int, cameras: tuple[str, ...] = STEREO) -> np.ndarray:
    """The frames (of ``n``) ``marker`` is in view of at least one camera, from ``truth.csv``'s columns."""
    mine = table["marker"] == marker
    seen = np.zeros(n, dtype=bool)
    frames = table["frame"][mine].astype(int)
    ok = frames < n
    seen[frames[ok]] = np.any([table[f"visible_{c}"][mine] > 0 for c in cameras], axis=0)[ok]
    return seen


def _has_source(folder: Path, name: str) -> bool:
    try:
        find_camera_source(folder, name)
    except ClipError:
        return False
    return True
