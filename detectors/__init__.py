"""Marker detection: the detector role and its registry (:mod:`detectors.base`), the blob
detector and colour ranges (:mod:`detectors.blob`), the stateful detectors (``blob``,
``meanshift``, ``camshift``) and the detect stage (:mod:`detectors.stage`)."""

from __future__ import annotations

from detectors import blob_tracker, meanshift  # noqa: F401  (the imports register blob, meanshift, camshift)
from detectors.base import _REGISTRY, Detector
from detectors.blob import MarkerColor
from pipeline.core.errors import StereotrackError


def registry() -> dict[str, type[Detector]]:
    """Every registered detector, the built-in ones first."""
    return dict(_REGISTRY)


def create_detector(name: str, markers: list[MarkerColor], groups: dict[str, list[str]] | None = None,
                    roi: tuple[int, int, int, int] | None = None) -> Detector:
    """A new detector of the registered kind ``name`` (one per camera)."""
    reg = registry()
    if name not in reg:
        raise StereotrackError(f"unknown detector {name!r} ({', '.join(reg)})")
    return reg[name](markers, groups, roi)
