"""How the compiled cores are compiled: numba's ``njit``, cached on disk (a fresh process loads a
core instead of compiling it), or not at all when ``STEREOTRACK_JIT=0`` is set before the package
is imported (:func:`pipeline.estimators.compiled.uncompiled` loads such a copy)."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

JIT = os.environ.get("STEREOTRACK_JIT", "1") != "0"


def kernel(fn: Callable | None = None, *, signature: str | None = None, inline: bool = False) -> Any:
    """Compile ``fn`` with numba on its first call (cached on disk across processes); with a
    ``signature``, for those argument types only (one compilation for every caller); ``inline``:
    copied into each caller, where constant sizes let the compiler unroll its loops. Without
    :data:`JIT` the function is returned as it is."""
    if not JIT:
        return (lambda f: f) if fn is None else fn
    from numba import njit

    def wrap(f: Callable) -> Any:
        if inline:
            return njit(cache=True, nogil=True, inline="always")(f)
        return njit(signature, cache=True, nogil=True)(f) if signature else njit(cache=True, nogil=True)(f)

    return wrap if fn is None else wrap(fn)
