"""The χ² quantiles written out in :mod:`pipeline.core.chi2` are scipy's, bit for bit; every other
argument goes to scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import chdtri
from scipy.special import gammaincinv as scipy_gammaincinv

from pipeline.core.chi2 import _CHDTRI, _GAMMAINCINV, chi2_upper, gammaincinv


@pytest.mark.parametrize("q", list(_GAMMAINCINV))
def test_the_written_out_quantiles_are_scipy_s(q):
    a = np.arange(1, len(_GAMMAINCINV[q]) + 1) / 2
    assert np.array_equal(gammaincinv(a, q), scipy_gammaincinv(a, q))
    for x in a:
        assert gammaincinv(x, q) == scipy_gammaincinv(x, q)


@pytest.mark.parametrize("gate", list(_CHDTRI))
def test_the_written_out_gates_are_scipy_s(gate):
    for dof in range(1, len(_CHDTRI[gate]) + 1):
        assert chi2_upper(dof, gate) == float(chdtri(dof, 1.0 - gate))


def test_other_arguments_go_to_scipy():
    assert gammaincinv(1.5, 0.95) == scipy_gammaincinv(1.5, 0.95)
    a = np.array([0.5, 7.0, 30.0])  # 30: beyond the table
    assert np.array_equal(gammaincinv(a, 0.5), scipy_gammaincinv(a, 0.5))
    assert np.array_equal(gammaincinv(np.array([1.25, 1.5]), 0.5), scipy_gammaincinv(np.array([1.25, 1.5]), 0.5))
    assert chi2_upper(2, 0.98) == float(chdtri(2, 1.0 - 0.98))
    assert chi2_upper(12, 0.9995) == float(chdtri(12, 1.0 - 0.9995))  # beyond the table


@pytest.mark.parametrize("q", [0.025, 0.975, 0.5, 0.05, 0.95, 1e-6, 1 - 1e-6])
def test_the_plain_python_quantile_is_scipy_s_to_its_stated_precision(q):
    """:func:`chi2_quantile` (the consistency figure's band) against scipy over small to large degrees
    of freedom, non-integer ones too: within 1e-14 relative for the band's quantiles, 5e-12 in the tails."""
    from pipeline.core.chi2 import chi2_quantile

    tol = 1e-14 if q in (0.025, 0.975) else 5e-12
    for dof in [0.5, 1, 1.5, 2, 3, 4, 7.3, 12, 30, 90, 120, 451, 3000]:
        want = 2 * float(scipy_gammaincinv(dof / 2, q))
        assert chi2_quantile(dof, q) == pytest.approx(want, rel=tol), dof
    with pytest.raises(ValueError):
        chi2_quantile(3, 1.0)
