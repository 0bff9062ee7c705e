"""Estimators, one module per method, all behind the protocol of :mod:`pipeline.estimators.base`.

Importing this package registers every method in :data:`REGISTRY` (name → class).
"""

from pipeline.estimators import (  # noqa: F401  (imported to register)
    alphabeta,
    ekf,
    four_point,
    kalman_bucy,
    kf3d,
    pnp_kf,
    spsa,
    spsa_vgg,
    triangulation,
    ukf,
)
from pipeline.estimators.base import REGISTRY, Estimator, Step, Track
from pipeline.estimators.four_point import TARGET_REGISTRY, TargetEstimator

POINT_METHODS = ["triangulation", "kf3d", "ekf", "ukf", "spsa_vgg", "spsa", "alphabeta", "alphabetagamma"]
TARGET_METHODS = ["four_point", "kalman_bucy", "pnp_kf"]


def create(name: str, rig, dt: float, config: dict | None = None) -> Estimator | TargetEstimator:
    """Build a registered estimator (point or four-point target method) by name."""
    from pipeline.errors import StereotrackError

    if name in REGISTRY:
        return REGISTRY[name](rig, dt, config)
    if name in TARGET_REGISTRY:
        return TARGET_REGISTRY[name](rig, dt, config)
    known = sorted([*REGISTRY, *TARGET_REGISTRY])
    raise StereotrackError(f"unknown method {name!r} (known: {', '.join(known)})")


__all__ = ["POINT_METHODS", "REGISTRY", "TARGET_METHODS", "TARGET_REGISTRY", "Estimator", "Step", "TargetEstimator",
           "Track", "create"]
