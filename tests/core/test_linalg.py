"""pipeline.core.linalg: scipy.linalg.expm's bits without importing scipy.linalg."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from scipy.linalg import block_diag as scipy_block_diag
from scipy.linalg import expm as scipy_expm

from pipeline.core import linalg


def _matrices() -> list[np.ndarray]:
    """Full, triangular (both ways), sparse triangular and diagonal matrices, 2×2 to 12×12, norms
    from 10⁻³ to 10² (no scaling up to many squarings), and the filters' own shapes."""
    rng = np.random.default_rng(7)
    out = []
    for n in (2, 3, 4, 6, 8, 12):
        for scale in (1e-3, 0.1, 1.0, 10.0, 100.0):
            m = rng.normal(size=(n, n)) * scale
            out += [m, np.triu(m), np.tril(m), np.diag(np.diag(m)), np.triu(m) * (rng.random((n, n)) < 0.5)]
    out += [np.array([[0.0, 1.0], [0.0, -0.2]]) * t for t in (0.0, 1e-3, 0.0333, 0.05)]  # a target channel
    out += [np.zeros((3, 3)), np.eye(4), np.array([[1.0, 2.0], [3.0, 4.0]])]
    return out


def test_expm_is_scipys_to_the_bit() -> None:
    for m in _matrices():
        ours, theirs = linalg.expm(m), scipy_expm(m)
        assert ours.shape == theirs.shape and ours.dtype == theirs.dtype
        assert np.array_equal(ours, theirs), m
    complex_ = np.array([[0.0, 1j], [1.0, 0.5]])  # scipy's own path, not cast to float
    assert np.array_equal(linalg.expm(complex_), scipy_expm(complex_))


def test_expm_is_the_exponential() -> None:
    """Independent of scipy: a rotation generator's exponential and a nilpotent one's series."""
    t = 0.7
    rot = linalg.expm(np.array([[0.0, -t], [t, 0.0]]))
    assert np.allclose(rot, [[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]], atol=1e-14)
    N = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 2.0], [0.0, 0.0, 0.0]])
    assert np.allclose(linalg.expm(N), np.eye(3) + N + N @ N / 2, atol=1e-14)


def test_block_diag_is_scipys() -> None:
    a, b = np.arange(4.0).reshape(2, 2), np.arange(6.0).reshape(3, 2) + 10
    assert np.array_equal(linalg.block_diag(a, b), scipy_block_diag(a, b))


def test_expm_without_the_kernel_falls_back_to_scipy(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(linalg, "_kernel", lambda: None)
    m = np.array([[0.1, 0.2], [-0.3, 0.4]])
    assert np.array_equal(linalg.expm(m), scipy_expm(m))


def test_expm_leaves_scipy_linalg_unimported() -> None:
    """The point of the module: a fresh process exponentiates full, triangular and diagonal
    matrices without paying scipy.linalg's import."""
    code = ("import sys, numpy as np; from pipeline.core.linalg import expm; m = np.arange(9.0).reshape(3, 3) / 10; "
            "[expm(x) for x in (m, np.triu(m), np.tril(m), np.diag(np.diag(m)))]; print('scipy.linalg' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
