"""Marker detection: the detector role and its registry (:mod:`detectors.base`), the blob
detector and colour ranges (:mod:`detectors.blob`), the stateful detectors (``blob``,
``meanshift``, ``camshift``) and the detect stage (:mod:`detectors.stage`)."""

from __future__ import annotations

from collections.abc import Collection

from detectors import blob_tracker, meanshift  # noqa: F401  (the imports register blob, meanshift, camshift)
from detectors.base import _REGISTRY, Detector, register
from detectors.blob import MarkerColor
from pipeline.core.errors import StereotrackError
from pipeline.core.plugins import DETECTOR_GROUP, load_entry_points

#: the entry-point group a plugin package registers its detectors under (as estimators use
#: ``stereotrack.estimators``): ``[project.entry-points."stereotrack.detectors"] NAME = "module:Class"``
ENTRY_POINT_GROUP = DETECTOR_GROUP
_plugins_loaded = False


def registry() -> dict[str, type[Detector]]:
    """Every registered detector: the built-in ones, then plugins from the ``stereotrack.detectors``
    entry points (loaded once; one that fails to load, or is no :class:`Detector`, is skipped with
    a warning)."""
    global _plugins_loaded
    if not _plugins_loaded:
        _plugins_loaded = True
        load_entry_points(ENTRY_POINT_GROUP, "detector", register)
    return dict(_REGISTRY)


def check_detector(name: str) -> None:
    """One error naming the known detectors when ``name`` is not one of them."""
    reg = registry()
    if name not in reg:
        raise StereotrackError(f"unknown detector {name!r} ({', '.join(reg)})")


def create_detector(name: str, markers: list[MarkerColor], groups: dict[str, list[str]] | None = None,
                    roi: tuple[int, int, int, int] | None = None, identical: Collection[str] = ()) -> Detector:
    """A new detector of the registered kind ``name`` (one per camera); ``identical``: the colour
    names of groups of identical markers, whose every blob it reports."""
    check_detector(name)
    cls = registry()[name]
    return cls(markers, groups, roi, identical) if identical else cls(markers, groups, roi)
