"""The one registry of estimators: the built-in methods register with :func:`register`; third-party
packages add theirs through the ``stereotrack.estimators`` entry points (see :func:`registry`)."""

from __future__ import annotations

import warnings

from pipeline.core.camera import StereoRig
from pipeline.core.errors import StereotrackError
from pipeline.core.plugins import ESTIMATOR_GROUP, load_entry_points
from pipeline.core.rig import Rig
from pipeline.estimators.base import Estimator, EstimatorConfig, Kind

ENTRY_POINT_GROUP = ESTIMATOR_GROUP
REGISTRY: dict[str, type[Estimator]] = {}
_plugins_loaded = False


def register(cls: type[Estimator]) -> type[Estimator]:
    """Class decorator: make an estimator available by name to the pipeline, CLI, reports,
    recordings and benchmarks. Third-party packages call it from a module named by an entry point
    of the group ``stereotrack.estimators`` (or point the entry point at the class itself)."""
    if not (isinstance(cls, type) and issubclass(cls, Estimator)):
        raise StereotrackError(f"{cls!r} is not an Estimator subclass")
    if not getattr(cls, "name", None):
        raise StereotrackError(f"estimator class {cls.__name__} has no name")
    prev = REGISTRY.get(cls.name)
    if prev is not None and origin(prev) != origin(cls):
        kept = "the built-in" if is_builtin(prev) else f"the first ({origin(prev)})"
        warnings.warn(f"estimator {origin(cls)} is named {cls.name!r}, which {origin(prev)} already is: {kept} is kept; "
                      "rename the plugin's method", stacklevel=2)
        return cls
    REGISTRY[cls.name] = cls
    return cls


def origin(cls: type) -> str:
    """Where an estimator class comes from, for messages: ``module.Class``."""
    return f"{cls.__module__}.{cls.__qualname__}"


def is_builtin(cls: type) -> bool:
    """Whether an estimator is one of stereotrack's own (not a plugin's)."""
    return cls.__module__.startswith("pipeline.estimators.")


def registry() -> dict[str, type[Estimator]]:
    """Every registered method (built-ins, then plugins from the ``stereotrack.estimators``
    entry points, loaded once; a plugin that fails to load is skipped with a warning)."""
    global _plugins_loaded
    if not _plugins_loaded:
        _plugins_loaded = True
        load_entry_points(ENTRY_POINT_GROUP, "estimator", register)
    return REGISTRY


def methods(kind: Kind | None = None) -> list[str]:
    """Registered method names (of one kind), in registration order."""
    return [n for n, c in registry().items() if kind is None or c.kind == kind]


def default_methods(target: bool = False) -> list[str]:
    """What ``estimate`` runs unless ``--methods`` says: every point method that is run by default
    (:attr:`Estimator.default`), then the target methods when the clip has a target."""
    reg = registry()
    point = [n for n, c in reg.items() if c.kind == "point" and c.default]
    return point + ([n for n, c in reg.items() if c.kind == "target" and c.default] if target else [])


def create(name: str, rig: StereoRig | Rig, dt: float, config: EstimatorConfig | dict | None = None,
           time_offset: float = 0.0) -> Estimator:
    """Build a registered estimator by name (``time_offset``: δ of the rig, for the methods that
    model it; see :attr:`Estimator.models_time_offset`)."""
    reg = registry()
    if name not in reg:
        raise StereotrackError(f"unknown method {name!r} (known: {', '.join(reg)})")
    if time_offset and reg[name].models_time_offset:
        return reg[name](rig, dt, config, time_offset=time_offset)
    return reg[name](rig, dt, config)
