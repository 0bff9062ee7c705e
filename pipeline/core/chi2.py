"""χ² quantiles without importing scipy.special where a default run needs them.

``scipy.special`` costs the estimate stage 0.15–0.2 s to import (``scipy._lib``'s array API layer
and ``numpy.f2py``), more than most methods take to run. The quantiles a run asks for by default —
χ²(dof)'s median and 95 % band for dof 1–12, its 95 % quantile (the recording's ellipsoids), and
the gates' upper quantiles at the default gate probabilities — are scipy's own values, written out
below (``tests/core/test_chi2.py`` recomputes each with scipy and compares them bit for bit); any
other argument is computed by scipy as before.
"""

from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

_GAMMAINCINV: dict[float, tuple[float, ...]] = {  # q → P⁻¹(dof/2, q) for dof = 1 … 12
    0.5: (
        0.227468211559786, 0.6931471805599455, 1.1829869421876689, 1.6783469900166612, 2.175730095547763,
        2.674060313723559, 3.1729055977607574, 3.672060748850897, 4.1714163461264775, 4.670908882795985,
        5.170499037195913, 5.67016118871207,
    ),
    (1 - 0.95) / 2: (
        0.0004910345585876292, 0.025317807984289897, 0.10789764131194898, 0.24220927854396507,
        0.4156058067433315, 0.6186721228956015, 0.8449345903386777, 1.089865373626325, 1.3501947499901792,
        1.623486390118421, 1.90787412611805, 2.201894253490851,
    ),
    (1 + 0.95) / 2: (
        2.511943093657444, 3.6888794541139354, 4.674201802248074, 5.571643390938898, 6.4162509970150134,
        7.22468766772396, 8.006382137314663, 8.767273069742323, 9.511383899320816, 10.241588675403694,
        10.9600246305106, 11.66833207932267,
    ),
    0.95: (  # the recording's 95 % covariance ellipsoids (dof 3)
        1.920729410347062, 2.9957322735539895, 3.9073639516255896, 4.743864518390577, 5.535248846758176,
        6.295793621871988, 7.033570224670084, 7.753656527932725, 8.459488802310224, 9.153519026637573,
        9.837568786341246, 10.513034908741535,
    ),
}
_CHDTRI: dict[float, tuple[float, ...]] = {  # gate → the upper 1 − gate quantile of χ² for dof = 1, 2, 3 (…)
    0.9995: (  # dof 1–11: a triangulation's residual over up to seven cameras (2k − 3)
        12.11566514639738, 15.201804919084385, 17.72999622894616, 19.99735499524785, 22.105326778207612,
        24.102798994983747, 26.01776770901503, 27.86804640338262, 29.66580810359642, 31.41981250740049,
        33.136615004168554,
    ),
    0.9999: (15.136705226623606, 18.420680743952584, 21.107513466160444),
    1 - 1e-6: (  # the joint check's, dof 1–12 (up to six cameras)
        23.92812697687947, 27.631021115871036, 30.66484970615427, 33.37684158165888, 35.88818687961042,
        38.25833637714585, 40.52183123411472, 42.70091392647789, 44.81093787062026, 46.86304684671568,
        48.86564276313385, 50.82525213880362,
    ),
}


def gammaincinv(a, q: float):
    """``scipy.special.gammaincinv(a, q)``: the inverse regularised lower incomplete gamma function
    (χ²(2a)'s ``q`` quantile is twice it), for a scalar or an array ``a``."""
    table = _GAMMAINCINV.get(q)
    a_arr = np.asarray(a, dtype=float)
    dof = 2 * a_arr
    if table is not None and np.all((dof == np.round(dof)) & (dof >= 1) & (dof <= len(table))):
        out = np.asarray([table[int(d) - 1] for d in dof.ravel()]).reshape(a_arr.shape)
        return float(out) if out.ndim == 0 else out
    from scipy.special import gammaincinv as scipy_gammaincinv

    return scipy_gammaincinv(a, q)


def chi2_upper(dof: int, gate: float) -> float:
    """``scipy.special.chdtri(dof, 1 − gate)``: the χ²(dof) value exceeded with probability ``1 − gate``."""
    table = _CHDTRI.get(gate)
    if table is not None and 1 <= dof <= len(table) and dof == int(dof):
        return table[int(dof) - 1]
    from scipy.special import chdtri

    return float(chdtri(dof, 1.0 - gate))


def chi2_quantile(dof: float, q: float) -> float:
    """χ²(dof)'s ``q`` quantile in plain Python (within 1e-14 of scipy's, relative, for the 95 % band's
    quantiles; 3e-12 in the far upper tail, q = 1 − 10⁻⁶): Halley's method on the
    regularised lower incomplete gamma function ``P(dof/2, x/2)`` (series below ``a + 1``, Lentz's
    continued fraction above; Press et al., *Numerical Recipes*, 3rd ed., §6.2), started from the
    Wilson–Hilferty approximation. For drawing a band where importing scipy.special would cost more
    than the figure; the estimates' and metrics' quantiles stay :func:`gammaincinv`'s."""
    if not (dof > 0 and 0.0 < q < 1.0):
        raise ValueError(f"chi2_quantile needs dof > 0 and 0 < q < 1, not {dof}, {q}")
    a = dof / 2.0
    h = 1.0 / (9.0 * a)
    x = a * max(1.0 - h + NormalDist().inv_cdf(q) * math.sqrt(h), 0.05) ** 3
    lg = math.lgamma(a)
    for _ in range(100):
        f = _lower_gamma(a, x, lg) - q
        d = math.exp((a - 1.0) * math.log(x) - x - lg)  # dP/dx
        u = f / d
        step = u / max(1.0 - 0.5 * u * ((a - 1.0) / x - 1.0), 0.1)  # Halley, damped where it would overshoot
        x_new = x - step if x - step > 0 else x / 2.0
        if abs(x_new - x) <= 1e-15 * x:
            return 2.0 * x_new
        x = x_new
    return 2.0 * x


def _lower_gamma(a: float, x: float, lg: float) -> float:
    """``P(a, x)``, the regularised lower incomplete gamma function (``lg``: ``ln Γ(a)``)."""
    front = math.exp(a * math.log(x) - x - lg)
    if x < a + 1.0:  # the series Σ xⁿ / (a (a+1) … (a+n))
        term = total = 1.0 / a
        n = a
        while abs(term) > abs(total) * 1e-17:
            n += 1.0
            term *= x / n
            total += term
        return total * front
    tiny = 1e-300  # Q(a, x) by the continued fraction (modified Lentz)
    b = x + 1.0 - a
    c, d = 1.0 / tiny, 1.0 / b
    frac = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = tiny if abs(d) < tiny else d
        c = b + an / c
        c = tiny if abs(c) < tiny else c
        d = 1.0 / d
        delta = d * c
        frac *= delta
        if abs(delta - 1.0) < 1e-16:
            break
    return 1.0 - front * frac
