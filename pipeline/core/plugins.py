"""Plugins: classes that other installed packages name under an entry-point group
(``stereotrack.estimators``, ``stereotrack.detectors``), registered with a role's registry."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from functools import cache
from typing import Any

#: the entry-point groups plugin packages register under, one per role
ESTIMATOR_GROUP, DETECTOR_GROUP = "stereotrack.estimators", "stereotrack.detectors"


@cache
def _entry_points() -> Any:
    """Every installed package's entry points, read once per process (each read walks every
    installed distribution: ~15 ms in a venv of a hundred packages, once for both roles)."""
    from importlib.metadata import entry_points

    return entry_points()


def load_entry_points(group: str, role: str, register: Callable[[type], object]) -> None:
    """Register every class the entry points of ``group`` name (an entry point may instead name a
    module whose import registers its classes); one that fails to load or to register is skipped
    with a warning naming it."""
    for ep in _entry_points().select(group=group):
        try:
            obj = ep.load()
            if isinstance(obj, type):
                register(obj)
        except Exception as exc:
            warnings.warn(f"{role} plugin {ep.name!r} ({ep.value}) failed to load: {exc}", stacklevel=3)


def has_plugins(*groups: str) -> bool:
    """Whether any installed package names an entry point in one of ``groups``."""
    return any(True for g in groups for _ in _entry_points().select(group=g))
