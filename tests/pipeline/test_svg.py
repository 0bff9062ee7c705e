"""The report's SVG figures: every drawn point lands where its data value belongs (linear, log and
inverted axes, NaN breaks a line), ticks are round numbers inside the axes, the limits hold what is
drawn, and the figures of a run are valid SVG that report.html carries inline."""

from __future__ import annotations

import math
import re
from xml.etree import ElementTree

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.present.svg import Figure, log_ticks, nice_ticks

NS = "{http://www.w3.org/2000/svg}"


def subpaths(d: str) -> list[np.ndarray]:
    """The (x, y) points of each subpath of SVG path data written as M/L commands."""
    return [np.array([[float(v) for v in p.split()] for p in re.findall(r"[ML]([^ML]+)", "M" + part)])
            for part in d.split("M")[1:]]


def inverse(ax, X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixels back to data, computed from the axes' box and limits (not from its transform)."""
    (x0, x1), (y0, y1) = ax.limits()
    bx, by, w, h = ax.box
    x = x0 + (X - bx) / w * (x1 - x0)
    f = (lambda v: math.log10(v)) if ax.ylog else (lambda v: v)
    lo, hi = f(y0), f(y1)
    frac = (Y - by) / h  # 0 at the top
    v = lo + frac * (hi - lo) if ax.yinvert else hi - frac * (hi - lo)
    return x, (10 ** v if ax.ylog else v)


@pytest.mark.parametrize("ylog,yinvert", [(False, False), (True, False), (False, True)])
def test_a_line_lands_where_its_values_belong(ylog, yinvert):
    rng = np.random.default_rng(3)
    x = np.arange(40.0)
    y = np.exp(rng.normal(1.0, 1.0, 40)) if ylog else rng.normal(0.0, 3.0, 40)
    y[[10, 25]] = np.nan
    fig = Figure(900, 400, ident="t")
    ax = fig.axes[0]
    ax.ylog, ax.yinvert = ylog, yinvert
    ax.line(x, y, "#123456", name="series")
    root = ElementTree.fromstring(fig.svg())
    d = next(p.get("d") for p in root.iter(NS + "path") if p.get("stroke") == "#123456")
    parts = subpaths(d)
    assert [len(p) for p in parts] == [10, 14, 14]  # broken at each NaN
    X, Y = np.concatenate(parts).T
    xs, ys = inverse(ax, X, Y)
    ok = np.isfinite(y)
    (x0, x1), (y0, y1) = ax.limits()
    px = (x1 - x0) / ax.box[2] * 0.06  # half the 0.1-pixel rounding, with room
    np.testing.assert_allclose(xs, x[ok], atol=px)
    if ylog:
        np.testing.assert_allclose(np.log10(ys), np.log10(y[ok]), atol=math.log10(y1 / y0) / ax.box[3] * 0.06)
    else:
        np.testing.assert_allclose(ys, y[ok], atol=(y1 - y0) / ax.box[3] * 0.06)
    assert fig.legend_labels() == {"series"}


@pytest.mark.parametrize("lo,hi,target", [(0, 1, 6), (-0.37, 2.9, 5), (1.5, 4.0, 7), (0, 149, 15), (1800, 2270, 8),
                                          (-1.07, 0.28, 9), (1e-3, 1.2e-3, 4), (-5e4, 3e5, 6)])
def test_ticks_are_round_numbers_inside_the_range(lo, hi, target):
    t = nice_ticks(lo, hi, target)
    step = np.diff(t)
    assert np.all(t >= lo - 1e-12) and np.all(t <= hi + 1e-12)
    assert np.allclose(step, step[0]) and target / 2.5 <= len(t) <= 2.5 * target + 1
    lead = step[0] / 10 ** math.floor(math.log10(step[0]))
    assert round(lead, 6) in (1.0, 2.0, 2.5, 5.0)


def test_log_ticks_name_decades_and_their_2_and_5_on_short_ranges():
    named, minor = log_ticks(0.8, 9.0)
    assert list(named) == [1.0, 2.0, 5.0] and 3.0 in minor and 0.9 in minor
    named, _ = log_ticks(0.05, 400.0)
    assert list(named) == [0.1, 1.0, 10.0, 100.0]


def test_limits_hold_the_band_and_equal_aspect_gives_one_scale():
    fig = Figure(1000, 400, 1, 2, "t")
    a, b = fig.axes
    a.ylog = True
    a.line([0, 1], [3.0, 6.0], "#000")
    a.band(0.8, 1.2)
    assert a.limits()[1][0] < 0.8 and a.limits()[1][1] > 6.0
    b.dots([100, 300], [200, 210], "#000")
    b.equal_aspect()
    (x0, x1), (y0, y1) = b.limits()
    assert (x1 - x0) / b.box[2] == pytest.approx((y1 - y0) / b.box[3]) and x0 <= 100 and x1 >= 300


@settings(max_examples=150, deadline=None)
@given(st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -1.0, 1e-300])),
                max_size=30), st.booleans(), st.booleans())
def test_any_series_gives_a_valid_figure_with_a_labelled_y_axis(values, ylog, yinvert):
    """NaN, infinities, zeros and negatives (on a log axis), one point or none, a constant, 1e±300:
    a parseable SVG with finite coordinates and at least one y label wherever a value is drawable."""
    fig = Figure(600, 300, ident="f")
    ax = fig.axes[0]
    ax.ylog, ax.yinvert = ylog, yinvert
    ax.line(np.arange(len(values), dtype=float), values, "#000", name="s")
    text = fig.svg()
    root = ElementTree.fromstring(text)
    assert "nan" not in text.lower() and "inf" not in text.lower()
    bx = ax.box[0]
    y_labels = [t for t in root.iter(NS + "text") if t.get("text-anchor") == "end" and float(t.get("x")) < bx]
    assert y_labels
