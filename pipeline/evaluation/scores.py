"""A track's per-frame scores, computed once per method and marker and shared by the estimates
CSV, ``metrics.json``, the report and the recording: the 3-D error against the truth, the filter's
NIS with its degrees of freedom, and the position NEES (:mod:`pipeline.evaluation.consistency`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.estimators.base import Track
from pipeline.evaluation import consistency


def errors_per_frame(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """3-D error (m) per frame over the frames both cover (NaN where either is missing)."""
    n = min(len(est), len(truth))
    return np.linalg.norm(np.asarray(est, float)[:n] - np.asarray(truth, float)[:n], axis=1)


@dataclass
class FrameScores:
    """One track's scores per frame. ``error`` and ``nees`` cover the frames the track and the
    truth both cover (None without truth, ``nees`` also None without a covariance); ``nis`` and
    ``nis_dof`` every frame of the track (None for a method without innovations)."""

    frames: int
    error: np.ndarray | None = None
    nees: np.ndarray | None = None
    nis: np.ndarray | None = None
    nis_dof: np.ndarray | None = None
    #: for a track of identical markers: the truth marker it follows in each frame (``""``: none)
    follows: list[str] | None = None

    def columns(self) -> np.ndarray:
        """frames × 3: NIS, its degrees of freedom, position NEES (NaN where not defined): the
        estimates CSV's consistency columns."""
        out = np.full((self.frames, 3), np.nan)
        if self.nis is not None and self.nis_dof is not None:
            out[:, 0], out[:, 1] = self.nis, np.where(self.nis_dof > 0, self.nis_dof, np.nan)
        if self.nees is not None:
            out[: len(self.nees), 2] = self.nees
        return out


def score_track(track: Track, truth_position: np.ndarray | None) -> FrameScores:
    """A track's :class:`FrameScores` against its marker's true positions (None: no truth)."""
    s = FrameScores(len(track.position), nis=track.nis, nis_dof=track.nis_dof)
    if track.nis is None or track.nis_dof is None:
        s.nis = s.nis_dof = None
    if truth_position is not None:
        T = truth_position[: len(track.position)]
        s.error = errors_per_frame(track.position, T)
        if track.covariance is not None:
            s.nees = consistency.nees(track, T)
    return s


def score_tracks(tracks: dict[str, Track], truth: dict[str, np.ndarray] | None) -> dict[str, FrameScores]:
    """Marker → :class:`FrameScores` of one method's tracks."""
    return {mk: score_track(t, truth.get(mk) if truth is not None else None) for mk, t in tracks.items()}
