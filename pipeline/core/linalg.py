"""The matrix exponential and block-diagonal matrices without importing ``scipy.linalg``.

``import scipy.linalg`` costs a fresh process 0.15–0.2 s (its array-API layer walks numpy's whole
namespace), more than the Kalman–Bucy and PnP + KF filters spend on a 150-frame clip. Those
filters need one function of it: ``expm``, by the scaling-and-squaring Padé algorithm of Al-Mohy
& Higham, *A new scaling and squaring algorithm for the matrix exponential*, SIAM J. Matrix Anal.
Appl. 31(3), 2009. :func:`expm` runs scipy's own compiled kernel of that algorithm
(``scipy.linalg._matfuncs_expm``, loaded from its file without the package around it) with the
steps of ``scipy.linalg.expm`` around it, so the result is scipy's to the bit (tested); where that
kernel is not found or takes other arguments (another scipy), it calls ``scipy.linalg.expm`` itself.
"""

from __future__ import annotations

import functools
import importlib.machinery
import importlib.util
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np


def block_diag(*blocks: np.ndarray) -> np.ndarray:
    """``scipy.linalg.block_diag`` of 2-D float blocks: each on the diagonal, zeros elsewhere."""
    rows, cols = sum(b.shape[0] for b in blocks), sum(b.shape[1] for b in blocks)
    out = np.zeros((rows, cols))
    r = c = 0
    for b in blocks:
        out[r : r + b.shape[0], c : c + b.shape[1]] = b
        r, c = r + b.shape[0], c + b.shape[1]
    return out


def expm(a: np.ndarray) -> np.ndarray:
    """``scipy.linalg.expm(a)`` of a square float matrix, to the bit, without importing
    ``scipy.linalg``: its steps (the diagonal case; the Padé kernel; the squaring, with a triangular
    matrix's diagonal and first off-diagonal recomputed exactly at each square, Higham's
    *Functions of Matrices* (2008) eq. 10.42, as Al-Mohy & Higham's code fragment 2.1 does)."""
    if np.iscomplexobj(a):
        return _scipy_expm(a)
    a = np.asarray(a, dtype=float)
    kernel = _kernel()
    if kernel is None or a.ndim != 2 or a.shape[0] != a.shape[1] or a.shape[0] < 2:
        return _scipy_expm(a)
    below, above = _off_diagonal(a.shape[0])
    flat = a.ravel()
    lower, upper = bool(flat[below].any()), bool(flat[above].any())
    if not (lower or upper):
        return np.diag(np.exp(np.diag(a)))
    Am = np.empty((5, *a.shape))  # the kernel's work space: A, A², A⁴, A⁶, A⁸ (scaled in place)
    Am[0] = a
    try:
        m, s = kernel.pick_pade_structure(Am)
        info = kernel.pade_UV_calc(Am, m)
    except TypeError:  # another scipy's kernel signature
        return _scipy_expm(a)
    if m < 0 or info != 0:  # an allocation or LAPACK failure: scipy's own call says which
        return _scipy_expm(a)
    eA = Am[0]
    if lower and upper:
        for _ in range(s):
            eA = eA @ eA
        return np.array(eA)
    if s:
        eA = _squared_triangular(a, eA, s, upper)
    return np.triu(eA) if upper else np.tril(eA)


def _squared_triangular(a: np.ndarray, eA: np.ndarray, s: int, upper: bool) -> np.ndarray:
    """``s`` squarings of a triangular matrix's scaled exponential, its diagonal and first
    off-diagonal set exactly after each (scipy.linalg.expm's triangular branch)."""
    diag_a = np.diag(a)
    np.einsum("ii->i", eA)[:] = np.exp(diag_a * 2 ** (-s))
    sd = np.diag(a, k=1 if upper else -1)
    for i in range(s - 1, -1, -1):
        eA = eA @ eA
        np.einsum("ii->i", eA)[:] = np.exp(diag_a * 2.0 ** (-i))
        exp_sd = _exp_sinch(diag_a * (2.0 ** (-i))) * (sd * 2 ** (-i))
        np.einsum("ii->i", eA[:-1, 1:] if upper else eA[1:, :-1])[:] = exp_sd
    return eA


def _exp_sinch(x: np.ndarray) -> np.ndarray:
    """``(e^{x_{i+1}} − e^{x_i}) / (x_{i+1} − x_i)``, ``e^{x_i}`` where they are equal (Higham 2008,
    eq. 10.42), as scipy computes it."""
    lexp_diff = np.diff(np.exp(x))
    l_diff = np.diff(x)
    mask_z = l_diff == 0.0
    lexp_diff[~mask_z] /= l_diff[~mask_z]
    lexp_diff[mask_z] = np.exp(x[:-1][mask_z])
    return lexp_diff


@functools.cache
def _off_diagonal(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of an n×n matrix's entries below and above its diagonal."""
    rows, cols = np.indices((n, n)).reshape(2, -1)
    return np.flatnonzero(rows > cols), np.flatnonzero(rows < cols)


def _scipy_expm(a: np.ndarray) -> np.ndarray:
    from scipy.linalg import expm as scipy_expm

    return scipy_expm(a)


@functools.cache
def _kernel() -> Any:
    """scipy's compiled ``_matfuncs_expm`` module, loaded from its file so that the ``scipy.linalg``
    package is not imported; None when this scipy has none."""
    try:
        spec = importlib.util.find_spec("scipy")
    except ImportError:
        return None
    if spec is None or spec.origin is None:
        return None
    folder = Path(spec.origin).parent / "linalg"
    found = [folder / f"_matfuncs_expm{suffix}" for suffix in importlib.machinery.EXTENSION_SUFFIXES]
    found = [p for p in found if p.is_file()]
    if not found:
        return None
    import scipy  # noqa: F401  (scipy's own start-up: on some platforms it makes its bundled libraries loadable)

    ext = importlib.util.spec_from_file_location("scipy.linalg._matfuncs_expm", found[0])
    if ext is None or ext.loader is None:
        return None
    module: ModuleType = importlib.util.module_from_spec(ext)
    try:
        ext.loader.exec_module(module)
    except ImportError:
        return None
    return module if hasattr(module, "pick_pade_structure") and hasattr(module, "pade_UV_calc") else None
