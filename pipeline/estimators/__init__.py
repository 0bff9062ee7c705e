"""Estimators, one module per method, all behind the one protocol of
:mod:`pipeline.estimators.base`.

Importing this package registers the built-in methods; :func:`registry` adds the plugins of the
``stereotrack.estimators`` entry-point group. Method lists are derived from it (:func:`methods`).
"""

# isort: off
from pipeline.estimators import (  # noqa: F401  (imported to register, in this order)
    triangulation,
    kf3d,
    ekf,
    ukf,
    spsa,
    spsa_vgg,
    spsa_stereo,
    alphabeta,
    four_point,
    kalman_bucy,
    pnp_kf,
    predict_only,
    imm,
)
# isort: on
from pipeline.estimators.base import Estimator, EstimatorConfig, Initiator, Step, Track
from pipeline.estimators.registration import ENTRY_POINT_GROUP, create, default_methods, methods, register, registry

__all__ = ["ENTRY_POINT_GROUP", "Estimator", "EstimatorConfig", "Initiator", "Step", "Track", "create", "default_methods",
           "methods", "register", "registry"]
