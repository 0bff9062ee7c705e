"""What the report draws, gathered once: from a run's results in memory (:func:`report_data`) or
read back from the stage files (:func:`load_report_data`) — positions per method (behind-camera
points hidden), filter consistency series, truth, detections and the markers' colours."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.clip import Clip, positions_from_columns
from pipeline.core.detections import load_detections
from pipeline.core.errors import StereotrackError
from pipeline.core.io import check_frame_column, read_csv, read_json_mapping
from pipeline.core.outputs import Outputs
from pipeline.core.rig import Rig
from pipeline.evaluation.identity import matched_truth
from pipeline.evaluation.metrics import runaways
from pipeline.evaluation.scores import FrameScores, errors_per_frame

if TYPE_CHECKING:
    from pipeline.estimate import EstimateResult
    from pipeline.estimators import Track

@dataclass
class ReportData:
    """What the report draws, read once from the stage files."""
    name: str
    out_dir: Path
    metrics: dict
    point: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # method → marker → positions
    target: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # method → CSV columns
    filters: dict[str, tuple[np.ndarray, np.ndarray, float]] = field(default_factory=dict)  # NEES/3, NIS/dof, n
    truth: dict[str, np.ndarray] | None = None
    target_truth: dict[str, np.ndarray] | None = None
    obs: dict[str, np.ndarray] = field(default_factory=dict)
    marker_colours: dict[str, list[int]] = field(default_factory=dict)
    #: method → track → 3-D error (m) per frame of the drawn positions (NaN where hidden): against
    #: its marker's truth, or for a track of identical markers the marker it follows in that frame
    errors: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    #: groups of identical markers → their members' names (whose truth the tracks are drawn beside)
    groups: dict[str, list[str]] = field(default_factory=dict)
    #: the clip's cameras, in the observations' order
    cameras: tuple[str, ...] = ("left", "right")

    @property
    def runaways(self) -> list[str]:
        return runaways(self.metrics)

    def add_method(self, est: EstimateResult, m: str, per: dict[str, Track], scores: dict[str, FrameScores]) -> None:
        """A point method's positions (behind-camera points hidden, on a copy) and its filter
        series, from its tracks and their scores in memory."""
        self.point[m] = {mk: t.position.copy() for mk, t in per.items()}
        _hide_behind(est.rig, {m: self.point[m]})
        self.errors[m] = {}
        for mk, P in self.point[m].items():
            if (e := scores[mk].error) is not None:
                self.errors[m][mk] = np.where(np.isnan(P[: len(e)]).any(axis=1), np.nan, e)
        if (s := _track_filter_series(scores)) is not None:
            self.filters[m] = s

    def tracking(self) -> list[str]:
        """Point methods that are drawn to scale (not runaways)."""
        return [m for m in self.point if m not in self.runaways]


def _hide_behind(rig: StereoRig | Rig, est: dict[str, dict[str, np.ndarray]]) -> None:
    """Points behind either camera set to NaN: counted in the metrics and the Checks section,
    never drawn as if they were metres in front of the rig."""
    for per in est.values():
        for P in per.values():
            with np.errstate(invalid="ignore"):
                P[np.any(rig.depths(P) <= 0, axis=1)] = np.nan


def _filter_series(cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A filter's NEES/3 and NIS/dof per frame (mean over markers) and markers per frame."""
    if not {"nis", "nis_dof", "nees"} <= set(cols) or not (np.isfinite(cols["nis"]).any()
                                                           or np.isfinite(cols["nees"]).any()):
        return None
    frames = cols["frame"].astype(int)
    n = int(frames.max()) + 1
    with np.errstate(all="ignore"):
        per = [np.bincount(frames, np.nan_to_num(v), n) / np.bincount(frames, np.isfinite(v), n)
               for v in (cols["nees"] / 3, cols["nis"] / cols["nis_dof"])]
    return per[0], per[1], max(1.0, len(frames) / n)


def load_report_data(clip: Clip, src: Path, out_dir: Path) -> ReportData:
    """The run's metrics and, for its methods only, their estimate CSVs (each read once), with
    truth, detections and the marker colours the detect stage recorded."""
    src_out = Outputs(src)
    mpath = src_out.metrics
    if not mpath.is_file():
        raise StereotrackError("no metrics.json: run `stereotrack estimate` first", mpath)
    metrics = read_json_mapping(mpath, "metrics")
    data = ReportData(clip.folder.name, out_dir, metrics)
    for m, entry in metrics.get("methods", {}).items():
        path = src_out.estimates(m)
        if not path.is_file():
            continue
        if entry.get("target"):
            data.target[m] = read_csv(path, ["t", "alpha", "distance"], numeric=["t", "alpha", "distance"])
            continue
        cols = read_csv(path, ["frame", "marker", "x", "y", "z"], numeric=["x", "y", "z"], finite=["frame"])
        check_frame_column(cols["frame"], None, path)
        data.point[m] = positions_from_columns(cols)[0]
        if (s := _filter_series(cols)) is not None:
            data.filters[m] = s
    truth = clip.truth()
    data.truth = truth.positions if truth is not None else None
    data.groups = clip.identical_groups()
    data.cameras = clip.cameras
    refs = {m: _references(per, data.truth, clip.group_truth()) for m, per in data.point.items()}
    if data.point and clip.has_calibration:
        _hide_behind(clip.rig(metrics.get("calibration_units")), data.point)
    data.errors = {m: {mk: errors_per_frame(data.point[m][mk], T) for mk, T in ref.items()} for m, ref in refs.items()}
    if (clip.folder / "target_truth.csv").is_file() and data.target:
        data.target_truth = read_csv(clip.folder / "target_truth.csv", ["t", "alpha", "distance"],
                                     numeric=["t", "alpha", "distance"])
    if src_out.detections.is_file():
        data.obs = load_detections(src_out.detections, cameras=clip.cameras)
    if src_out.detect_info.is_file():
        data.marker_colours = read_json_mapping(src_out.detect_info, "detect record").get("marker_colours", {})
    return data


def _references(per: dict[str, np.ndarray], truth: dict[str, np.ndarray] | None,
                groups: dict[str, dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Each track's true positions, in the tracks' order: its marker's, or for a track of identical
    markers (``<group>#<n>``) the marker it follows frame by frame, as the estimate stage scored it."""
    refs = {mk: truth[mk] for mk in per if truth is not None and mk in truth}
    for g, members in groups.items():
        if mine := {mk: P for mk, P in per.items() if mk.startswith(g + "#")}:
            refs.update(matched_truth(members, mine)[0])
    return {mk: refs[mk] for mk in per if mk in refs}


def _track_filter_series(scores: dict[str, FrameScores]) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A filter's NEES/3 and NIS/dof per frame from its tracks' scores in memory: the columns its
    estimates CSV holds, through :func:`_filter_series`."""
    cols = [s.columns() for s in scores.values()]
    c = np.vstack(cols)
    return _filter_series({"frame": np.concatenate([np.arange(len(x)) for x in cols]), "nis": c[:, 0],
                           "nis_dof": c[:, 1], "nees": c[:, 2]})


def report_data(clip: Clip, est: EstimateResult, marker_colours: dict[str, list[int]], out_dir: Path,
                data: ReportData | None = None) -> ReportData:
    """The report's data from a run's results in memory: what :func:`load_report_data` would read
    back from the stage files, read from nothing (the calibration included). ``data``: what
    :meth:`ReportData.add_method` already took of methods whose tracks were not kept."""
    data = data or ReportData(clip.folder.name, out_dir, {})
    data.name, data.out_dir, data.metrics = clip.folder.name, out_dir, est.metrics
    data.truth, data.groups, data.cameras = est.truth_positions, clip.identical_groups(), est.rig.names
    data.obs, data.marker_colours = dict(est.observations), dict(marker_colours)
    for m, per in est.tracks.items():
        if m not in data.point:
            data.add_method(est, m, per, est.scores[m])
    for m, t in est.target_tracks.items():
        data.target[m] = {"t": np.arange(len(t.position)) * est.dt, "alpha": t.extra["alpha"],
                          "distance": t.extra["distance"]}
    tg = est.target
    if tg is not None and tg.alpha is not None and tg.distance is not None and est.target_tracks:
        data.target_truth = {"t": np.arange(len(tg.alpha)) * est.dt, "alpha": tg.alpha, "distance": tg.distance}
    return data
