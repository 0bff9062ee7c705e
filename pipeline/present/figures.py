"""The report's matplotlib figures (trajectories, error per frame, image-plane tracks, the target's
α and z, filter consistency), each a pure function of :class:`~pipeline.present.report_data.ReportData`;
axes are set by the methods that track, and a runaway method is clipped and named."""

from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from functools import partial
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.forked import forked_map
from pipeline.present.report_data import ReportData
from pipeline.present.style import TRUTH_STYLE, marker_rgb, method_colour, method_linestyle

if TYPE_CHECKING:
    pass

#: figure resolution: sharp on a laptop screen, cheap to encode
DPI = 100
#: frames in the moving mean of the consistency figure
CONSISTENCY_WINDOW = 15


def _legend(fig, axes) -> None:
    """One legend for the figure, right of the axes (never over the data), listing every series."""
    handles: dict[str, object] = {}
    for ax in np.atleast_1d(axes):
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    _margins(fig, 0.84 if handles else 1.0)
    if handles:
        fig.legend(list(handles.values()), list(handles), fontsize=8, loc="center left", bbox_to_anchor=(0.845, 0.5),
                   ncol=2 if len(handles) > 16 else 1)


def _margins(fig, right: float) -> None:
    """Fixed margins in inches (room for tick labels, axis labels and titles) instead of
    ``tight_layout``, which measures every tick label's text and took half of each figure's time;
    the axes end at ``right`` (the legend's column beyond)."""
    w, h = fig.get_size_inches()
    left, right, bottom, top = 0.85 / w, right - 0.1 / w, 0.6 / h, 1 - 0.45 / h
    cols = max(1, len({round(ax.get_position().x0, 3) for ax in fig.axes}))
    rows = max(1, len({round(ax.get_position().y0, 3) for ax in fig.axes}))
    gap_w, gap_h = 0.9, 1.1  # inches between axes: the next one's tick labels and y label; a title and x label

    def space(extent: float, n: int, gap: float) -> float:  # matplotlib's spacing: a gap over one axis' extent
        return gap / max(extent / n - gap * (n - 1) / n, 0.1)

    fig.subplots_adjust(left=left, right=right, bottom=bottom, top=top, wspace=space((right - left) * w, cols, gap_w),
                        hspace=space((top - bottom) * h, rows, gap_h))


def _limits(arrays: list[np.ndarray], pad: float = 0.08) -> tuple[float, float] | None:
    """Axis limits holding the finite values of ``arrays`` (0.5–99.5 percentiles), padded."""
    vals = np.concatenate([a[np.isfinite(a)] for a in arrays]) if arrays else np.empty(0)
    if not vals.size:
        return None
    lo, hi = np.percentile(vals, [0.5, 99.5])
    span = max(hi - lo, 1e-3)
    return float(lo - pad * span), float(hi + pad * span)


def _plain_log_labels(ax) -> None:
    """Log-axis ticks as plain numbers (1, 2, 5, 10 …), not powers of ten; minor ticks labelled
    only at 2 and 5 of each decade, so labels never crowd."""
    import math

    from matplotlib.ticker import FormatStrFormatter, FuncFormatter

    def minor(v: float, _pos: int) -> str:
        lead = round(v / 10 ** math.floor(math.log10(v)), 6) if v > 0 else 0
        return f"{v:g}" if lead in (2.0, 5.0) else ""

    ax.yaxis.set_major_formatter(FormatStrFormatter("%g"))
    ax.yaxis.set_minor_formatter(FuncFormatter(minor))


def _runaway_note(data: ReportData, drawn: list[str]) -> str:
    off = [m for m in data.runaways if m in drawn]
    if not off:
        return ""
    key = "rmse" if data.metrics.get("has_truth") else "reprojection_rmse_px"
    unit = (lambda v: f"{1000 * v:.3g} mm") if key == "rmse" else (lambda v: f"{v:.3g} px")
    return ("; axes set by the methods that track: " + ", ".join(
        f"{m} (RMSE {unit(data.metrics['methods'][m][key])})" for m in off) + " run off them")


#: the most points one line of a figure holds: a figure is 1,200 pixels wide (12 in at :data:`DPI`),
#: so a longer series is thinned before it is drawn (which also keeps a long clip's figures from
#: holding several copies of every frame of every track)
MAX_LINE_POINTS = 2000


def _thin(*columns: np.ndarray) -> tuple[np.ndarray, ...]:
    """Every k-th point of a path (and its last) when it has over :data:`MAX_LINE_POINTS`."""
    n = len(columns[0])
    step = -(-n // MAX_LINE_POINTS)
    if step <= 1:
        return columns
    idx = np.r_[np.arange(0, n - 1, step), n - 1]
    return tuple(c[idx] for c in columns)


def _envelope(y: np.ndarray, x: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """A per-frame series as (x, y) of at most :data:`MAX_LINE_POINTS` points: each bucket of
    frames gives its smallest and its largest value, in frame order, so spikes stay visible and a
    bucket with no value stays a gap."""
    n = len(y)
    x = np.arange(n) if x is None else x
    step = -(-n // (MAX_LINE_POINTS // 2))
    if step <= 1:
        return x, y
    Y = np.concatenate([y, np.full(-n % step, np.nan)]).reshape(-1, step)
    ok = np.isfinite(Y)
    lo, hi = np.where(ok, Y, np.inf).argmin(axis=1), np.where(ok, Y, -np.inf).argmax(axis=1)
    base = np.arange(len(Y)) * step
    idx = np.stack([base + np.minimum(lo, hi), base + np.maximum(lo, hi)], axis=1).ravel()
    idx = np.unique(idx[idx < n])
    return x[idx], y[idx]


def fig_trajectories(data: ReportData, plt) -> tuple[object, str] | None:
    """Top (x–z) and side (y–z) views of every marker: truth dashed black, each method its colour."""
    if not data.point:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    drawn = {mk for per in data.point.values() for mk in per}
    markers = sorted(drawn | {name for g, names in data.groups.items() if any(mk.startswith(g + "#") for mk in drawn)
                              for name in names})
    keep = data.tracking()
    for ax, i in zip(axes, (0, 1), strict=True):
        for mk in markers:
            if data.truth and mk in data.truth:
                ax.plot(*_thin(data.truth[mk][:, 2], data.truth[mk][:, i]), label="truth", **TRUTH_STYLE)
            for meth, per in data.point.items():
                if mk in per:
                    ax.plot(*_thin(per[mk][:, 2], per[mk][:, i]), method_linestyle(meth), lw=1,
                            color=method_colour(meth), label=meth)
        shown = [per[mk][:, j] for per in (data.point[m] for m in keep) for mk in per for j in (2, i)]
        truth = [T[:, j] for T in (data.truth or {}).values() for j in (2, i)]
        zx = _limits([a for a in shown[::2] + truth[::2]]), _limits([a for a in shown[1::2] + truth[1::2]])
        if zx[0]:
            ax.set_xlim(*zx[0])
        if zx[1]:
            ax.set_ylim(*(zx[1][::-1] if i == 1 else zx[1]))
        ax.set(xlabel="z (m)", ylabel=("x", "y")[i] + " (m)", title=("top view: x vs z", "side view: y vs z")[i])
        ax.grid(alpha=0.3)
    _legend(fig, axes)
    return fig, "Trajectories, top and side views" + _runaway_note(data, list(data.point))


def fig_error(data: ReportData, plt) -> tuple[object, str] | None:
    """3-D error per frame (mean over markers), log scale, each method its colour."""
    if not any(data.errors.values()):
        return None
    fig, ax = plt.subplots(figsize=(12, 4.5))
    errs = {}
    for meth, per in data.errors.items():
        if e := list(per.values()):
            n = min(len(x) for x in e)
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                errs[meth] = np.nanmean([x[:n] for x in e], axis=0) * 1000
            ax.semilogy(*_envelope(errs[meth]), method_linestyle(meth), color=method_colour(meth), lw=1, label=meth)
    shown = [errs[m][errs[m] > 0] for m in data.tracking() if m in errs]
    lim = _limits([np.log10(a) for a in shown], pad=0.05)
    if lim:
        ax.set_ylim(10 ** lim[0], 10 ** lim[1])
    _plain_log_labels(ax)
    ax.set(xlabel="frame", ylabel="3-D error (mm), mean over markers")
    ax.grid(alpha=0.3, which="both")
    _legend(fig, ax)
    return fig, "3-D error per frame" + _runaway_note(data, list(errs))


def fig_image_tracks(data: ReportData, plt) -> tuple[object, str] | None:
    """Each camera's detections, one colour per marker (the marker's own)."""
    if not data.obs:
        return None
    n = len(data.cameras)
    cols = min(n, 2) if n <= 4 else 3
    rows = -(-n // cols)
    fig, grid = plt.subplots(rows, cols, figsize=(12, 4.5 * rows), squeeze=False)
    axes = list(grid.ravel()[:n])
    for ax in grid.ravel()[n:]:
        ax.remove()
    for c, ax in enumerate(axes):
        for i, (mk, Y) in enumerate(sorted(data.obs.items())):
            ax.plot(*_thin(Y[:, 2 * c], Y[:, 2 * c + 1]), ".", ms=2, label=mk,
                    color=np.array(marker_rgb(data.marker_colours, mk, i)) / 255)
        ax.set(xlabel="u (px)", ylabel="v (px)", title=f"{data.cameras[c]} camera: detections (px)")
        ax.invert_yaxis()
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    _legend(fig, axes)
    return fig, "Image-plane tracks (detections)"


def fig_target(data: ReportData, plt) -> tuple[object, str] | None:
    """The four-point target's angle α and distance z over time: truth and each target method."""
    if not data.target:
        return None
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for ax, col, ylabel in ((axes[0], "alpha", "α (mrad)"), (axes[1], "distance", "z (mm)")):  # as the tables
        if data.target_truth is not None:
            ax.plot(*_envelope(1000 * np.asarray(data.target_truth[col], dtype=float), data.target_truth["t"]),
                    label="truth", **TRUTH_STYLE)
        for meth, cols in data.target.items():
            ax.plot(*_envelope(1000 * np.asarray(cols[col], dtype=float), cols["t"]), method_linestyle(meth),
                    color=method_colour(meth), lw=1, label=meth)
        ax.set(xlabel="t (s)", ylabel=ylabel, title=f"target {ylabel.split()[0]}")
        ax.grid(alpha=0.3)
    _legend(fig, axes)
    return fig, "Four-point target: α and z"


def fig_consistency(data: ReportData, plt) -> tuple[object, str] | None:
    """NEES/3 and NIS/dof of each filter (moving mean over :data:`CONSISTENCY_WINDOW` frames, all
    markers) against the 95 % band of that mean: the quantities of the consistency table."""
    from pipeline.core.chi2 import chi2_quantile

    if not data.filters:
        return None
    w = CONSISTENCY_WINDOW
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for i, (ax, title, dof) in enumerate(((axes[0], "NEES / 3, position, against truth", 3),
                                          (axes[1], "NIS / dof of the filter's innovations", 4))):
        per_frame = []
        for meth, series in data.filters.items():
            v, ok = series[i], np.isfinite(series[i])
            if not ok.any():
                continue
            with np.errstate(all="ignore"):
                mean = np.convolve(np.where(ok, v, 0), np.ones(w), "same") / np.convolve(ok, np.ones(w), "same")
            ax.semilogy(*_envelope(mean), method_linestyle(meth), color=method_colour(meth), lw=1, label=meth)
            per_frame.append(series[2])
        if per_frame:
            k = round(dof * w * float(np.median(per_frame)))  # χ² degrees of freedom in one moving mean
            band = chi2_quantile(k, 0.025) / k, chi2_quantile(k, 0.975) / k  # no scipy.special import (0.3 s)
            ax.axhspan(*band, color="0.85", zorder=0, label="95 % band")
        _plain_log_labels(ax)
        ax.set(xlabel="frame", ylabel=f"moving mean over {w} frames", title=title)
        ax.grid(alpha=0.3, which="both")
    _legend(fig, axes)
    return fig, "Filter consistency: NEES/3 and NIS/dof (1 when the covariance matches the errors)"


FIGURES: list[tuple[str, Callable]] = [("trajectories", fig_trajectories), ("error", fig_error),
                                       ("image_tracks", fig_image_tracks), ("target", fig_target),
                                       ("consistency", fig_consistency)]


def _release_lines(fig) -> None:
    """Empty a drawn figure's lines now: a figure is a web of reference cycles that only Python's
    cycle collector frees, and until it runs each line holds several copies of its points (a full
    collection per figure cost more than drawing a small clip's figure)."""
    for ax in fig.axes:
        for line in ax.lines:
            line.set_data([], [])
            line.recache_always()


def render_figures(data: ReportData, progress: Callable[[int, int], None] | None = None, workers: int = 1
                   ) -> list[tuple[str, str, bytes]]:
    """(name, caption, PNG bytes) of every figure the run has; ``progress`` gets (done, of).
    ``workers``: processes the figures are drawn in, forked from this one (the same bytes as one)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot  # (imported once, here, not in each worker)

    out = []
    if progress is not None:
        progress(0, len(FIGURES))
    for k, drawn in enumerate(forked_map(partial(_draw, data), FIGURES, workers)):
        if drawn is not None:
            out.append(drawn)
        if progress is not None:
            progress(k + 1, len(FIGURES))
    return out


def _draw(data: ReportData, figure: tuple[str, Callable]) -> tuple[str, str, bytes] | None:
    """One figure of :data:`FIGURES` as (name, caption, PNG bytes), or None when the run has nothing for it."""
    import matplotlib.pyplot as plt

    name, make = figure
    made = make(data, plt)
    if made is None:
        return None
    fig, caption = made
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    plt.close(fig)
    _release_lines(fig)
    return name, caption, buf.getvalue()
