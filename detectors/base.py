"""The detector role: one object per camera that finds the markers in each frame and owns its
search state (windows, recent sizes, labels, tracked histograms), and the registry the CLI's
choices come from. Detectors register themselves like estimators do (Stone Soup's one base per
role); ``tests/detectors/test_detector_protocol.py`` runs every registered one through the same checks."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Collection
from typing import ClassVar

import numpy as np

from detectors.blob import Detection, MarkerColor
from pipeline.core.errors import StereotrackError


class Detector(ABC):
    """Finds each marker in one camera's frames, one frame at a time.

    ``markers``: the colour ranges to find; ``groups``: a one-colour four-point target's colour
    name → its four point names (the detector labels the points); ``roi``: a user's first search
    window (x, y, w, h), for detectors that start from one."""

    #: the name the CLI and ``detect.json`` use
    name: ClassVar[str]
    #: whether it can label a one-colour four-point target's points
    labels_targets: ClassVar[bool] = False
    #: whether it reports every blob of a group of identical markers (not one per colour)
    reports_many: ClassVar[bool] = False
    #: whether its objects may work in a process forked for their camera (no GPU context, thread or
    #: open device of their own to lose in the fork); the detect stage runs the others in threads
    forks: ClassVar[bool] = False

    def __init__(self, markers: list[MarkerColor], groups: dict[str, list[str]] | None = None,
                 roi: tuple[int, int, int, int] | None = None, identical: Collection[str] = ()) -> None:
        if not markers:
            raise StereotrackError("no markers to detect: give --markers or a clip with clip.json")
        if groups and not self.labels_targets:
            raise StereotrackError(f"{self.name} tracks one point per colour: use blob for a one-colour target")
        if identical and not self.reports_many:
            raise StereotrackError(f"{self.name} tracks one point per colour: use blob for identical markers "
                                   f"({', '.join(sorted(identical))})")
        self.markers, self.groups, self.roi = markers, dict(groups or {}), roi
        #: the groups of identical markers (colour names) whose every blob is reported, unlabelled
        self.identical = frozenset(identical)

    @abstractmethod
    def detect(self, frame: np.ndarray) -> list[Detection]:
        """The markers found in this BGR frame: at most one detection per marker (or per point of
        a target), sub-pixel, in OpenCV's pixel convention."""

    def reset(self) -> None:  # noqa: B027  (a detector without search state keeps nothing to forget)
        """Forget the search state (the camera has no frame here: a dropped or missing frame)."""


_REGISTRY: dict[str, type[Detector]] = {}


def register(cls: type[Detector]) -> type[Detector]:
    """Class decorator: make a detector available by its ``name``."""
    if not (isinstance(cls, type) and issubclass(cls, Detector)):
        raise TypeError(f"{cls!r} is not a detectors.base.Detector subclass")
    _REGISTRY[cls.name] = cls
    return cls
