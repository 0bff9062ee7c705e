"""Estimators, one module per method, all behind the protocol of :mod:`pipeline.estimators.base`.

Importing this package registers every method in :data:`REGISTRY` (name → class).
"""

from pipeline.estimators import (  # noqa: F401  (imported to register)
    alphabeta,
    ekf,
    kf3d,
    spsa,
    spsa_vgg,
    triangulation,
    ukf,
)
from pipeline.estimators.base import REGISTRY, Estimator, Step, Track

POINT_METHODS = ["triangulation", "kf3d", "ekf", "ukf", "spsa_vgg", "spsa", "alphabeta", "alphabetagamma"]


def create(name: str, rig, dt: float, config: dict | None = None) -> Estimator:
    """Build a registered estimator by name (a clear error for unknown names)."""
    from pipeline.errors import StereotrackError

    if name not in REGISTRY:
        raise StereotrackError(f"unknown method {name!r} (known: {', '.join(sorted(REGISTRY))})")
    return REGISTRY[name](rig, dt, config)


__all__ = ["POINT_METHODS", "REGISTRY", "Estimator", "Step", "Track", "create"]
