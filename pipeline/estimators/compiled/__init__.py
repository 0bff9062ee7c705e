"""Compiled cores of the estimators whose per-frame loop is the cost, one module per method beside
its interpreted twin: Algorithm 1 (:mod:`.spsa`), the EKF and the Rauch–Tung–Striebel backward pass
of the smoothers (:mod:`.ekf`) and ``spsa_stereo``'s frame update (:mod:`.spsa_stereo`), on one
Joseph update and fixed-size linear algebra (:mod:`.linalg`) and the camera's own measurement model
(:func:`pipeline.core.camera.linearize_point`). A core's settings and state travel as records
(named tuples of arrays, structured records read by field name), not as index constants.

Each core is plain Python over float arrays, compiled by numba (``njit``, cached on disk, so a fresh
process loads it instead of compiling) and run as it is when ``STEREOTRACK_JIT=0`` is set before
this package is imported (:func:`uncompiled` loads such a copy: the tests run both and compare).
The estimators import this package on the first ``run`` that takes the compiled path
(:func:`pipeline.estimators.base.use_compiled`), so neither ``import pipeline``, the streaming
``step`` nor a short clip pays for numba.

Algorithm 1 and ``spsa_stereo`` are the same operations in the same order as the estimators' own
(after Krivokon 2011, Algorithm 1 and App. I); the EKF differs in rounding only (the prediction by
blocks, the covariance's upper triangle mirrored, small inverses by Gauss–Jordan rather than
LAPACK), and the tests hold every path equal to 1e-9.
"""

from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path
from types import ModuleType

import numpy as np

from ._jit import JIT, kernel
from .ekf import EKFModel, EKFOutput, ekf_batch, ekf_frames, new_output, new_track, rts_backward, stereo_linearize
from .linalg import inv_small, joseph_update, mm6
from .spsa import SPSAGains, new_state, spsa_batch, spsa_frames
from .spsa_stereo import (
    PARAMS,
    ST_CONSISTENT,
    ST_DONE,
    ST_RESTART,
    ST_TRI,
    StereoFrames,
    StereoOutput,
    spsa_stereo_frames,
    st_begin,
    state_of,
)
from .spsa_stereo import new_params as new_stereo_params
from .spsa_stereo import new_track as new_stereo_track

__all__ = ["JIT", "PARAMS", "ST_CONSISTENT", "ST_DONE", "ST_RESTART", "ST_TRI", "EKFModel", "EKFOutput", "SPSAGains",
           "StereoFrames", "StereoOutput", "ekf_batch", "ekf_frames", "inv_small", "joseph_update", "kernel", "mm6",
           "new_output", "new_state", "new_stereo_params", "new_stereo_track", "new_track", "rts_backward",
           "spsa_batch", "spsa_frames", "spsa_stereo_frames", "st_begin", "state_of", "stereo_linearize",
           "uncompiled", "warm_up"]


def uncompiled() -> ModuleType:
    """This package loaded once more with every kernel left as plain Python (for the tests)."""
    name = __name__ + "_python"
    if name in sys.modules:
        return sys.modules[name]
    here = Path(__file__).parent
    spec = importlib.util.spec_from_file_location(name, here / "__init__.py", submodule_search_locations=[str(here)])
    assert spec is not None and spec.loader is not None  # a package that exists: this one
    module = importlib.util.module_from_spec(spec)
    before = os.environ.get("STEREOTRACK_JIT")
    os.environ["STEREOTRACK_JIT"] = "0"
    sys.modules[name] = module  # its modules' relative imports resolve inside the copy
    try:
        spec.loader.exec_module(module)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    finally:
        if before is None:
            del os.environ["STEREOTRACK_JIT"]
        else:
            os.environ["STEREOTRACK_JIT"] = before
    return module


_warm: set[str] = set()


def warm_up(*names: str) -> None:
    """Compile, or load from numba's cache, the named kernels (``ekf_frames``, ``spsa_frames``,
    ``rts_backward``, ``spsa_stereo_frames``; all without names) once per process, each with the
    argument types the estimators pass, so that a timed loop times arithmetic, not compilation."""
    for name in names or ("ekf_frames", "spsa_frames", "rts_backward", "spsa_stereo_frames"):
        if name not in _warm:
            _warm.add(name)
            if JIT:
                _WARM_UPS[name]()


def _warm_ekf() -> None:
    n, I6 = 3, np.eye(6)
    model = EKFModel(np.ones((2, 3, 4)), 0.0, 0.1, I6, np.eye(4), np.inf, 8, np.inf)
    ekf_frames(np.full((n, 4), np.nan), 1, 0, model, new_track(np.zeros(6), I6.copy()), new_output(n))


def _warm_spsa() -> None:
    n = 3
    spsa_frames(np.full((n, 4), np.nan), np.zeros(n, np.bool_), np.zeros(n, np.bool_), np.ones((2, 6)), np.ones((2, 12)),
                SPSAGains(0.1, 0.01, 0.03), new_state(np.zeros(6)), np.zeros((n, 6)), np.ones(n, dtype=np.bool_))


def _warm_spsa_stereo() -> None:
    n, f = 3, np.zeros
    prm = new_stereo_params(R=f(9), t=f(3), b=1.0, AL=f(12), AR=f(12), poses=f((2, 12)), f2=f(2),
                            **dict.fromkeys(("dt", "c", "far", "sweeps", "cost_gate", "nis_gate", "sigma2", "nmax", "kd",
                                             "amin_d", "runlen", "restart"), 1.0))
    frames = StereoFrames(np.full((n, 4), np.nan), f(n, np.bool_), f(n, np.bool_), f(n), f((n, 4)))
    out = StereoOutput(f((n, 6)), np.ones(n, dtype=np.bool_), f(n), f(n), f(n), f(n))
    spsa_stereo_frames(frames, 0, prm, new_stereo_track(1.0), out)


def _warm_rts() -> None:
    rts_backward(np.zeros((2, 6)), np.tile(np.eye(6), (2, 1, 1)), 0.1, np.eye(6))


_WARM_UPS = {"ekf_frames": _warm_ekf, "spsa_frames": _warm_spsa, "spsa_stereo_frames": _warm_spsa_stereo,
             "rts_backward": _warm_rts}
