"""The report's figures (trajectories, error per frame, image-plane tracks, the target's α and z,
filter consistency) as SVG, each a pure function of :class:`~pipeline.present.report_data.ReportData`;
axes are set by the methods that track, and a runaway method is clipped and named."""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from pipeline.present.report_data import ReportData
from pipeline.present.style import TRUTH_STYLE, marker_rgb, method_hex, method_linestyle, rgb_hex
from pipeline.present.svg import Axes, Figure

#: frames in the moving mean of the consistency figure
CONSISTENCY_WINDOW = 15


def _limits(arrays: list[np.ndarray], pad: float = 0.08) -> tuple[float, float] | None:
    """Axis limits holding the finite values of ``arrays`` (0.5–99.5 percentiles), padded."""
    vals = np.concatenate([a[np.isfinite(a)] for a in arrays]) if arrays else np.empty(0)
    if not vals.size:
        return None
    lo, hi = np.percentile(vals, [0.5, 99.5])
    span = max(hi - lo, 1e-3)
    return float(lo - pad * span), float(hi + pad * span)


def _runaway_note(data: ReportData, drawn: list[str]) -> str:
    off = [m for m in data.runaways if m in drawn]
    if not off:
        return ""
    key = "rmse" if data.metrics.get("has_truth") else "reprojection_rmse_px"
    unit = (lambda v: f"{1000 * v:.3g} mm") if key == "rmse" else (lambda v: f"{v:.3g} px")
    return ("; axes set by the methods that track: " + ", ".join(
        f"{m} (RMSE {unit(data.metrics['methods'][m][key])})" for m in off) + " run off them")


#: the most points one line of a figure holds: a figure is 1,200 pixels wide,
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


def _truth_line(ax: Axes, x, y) -> None:
    ax.line(x, y, *TRUTH_STYLE, name="truth")


def _method_line(ax: Axes, x, y, meth: str) -> None:
    ax.line(x, y, method_hex(meth), method_linestyle(meth), 1.0, name=meth)


def fig_trajectories(data: ReportData) -> tuple[Figure, str] | None:
    """Top (x–z) and side (y–z) views of every marker: truth dashed black, each method its colour."""
    if not data.point:
        return None
    fig = Figure(1200, 500, 1, 2, "trajectories")
    drawn = {mk for per in data.point.values() for mk in per}
    markers = sorted(drawn | {name for g, names in data.groups.items() if any(mk.startswith(g + "#") for mk in drawn)
                              for name in names})
    keep = data.tracking()
    for ax, i in zip(fig.axes, (0, 1), strict=True):
        for mk in markers:
            if data.truth and mk in data.truth:
                _truth_line(ax, *_thin(data.truth[mk][:, 2], data.truth[mk][:, i]))
            for meth, per in data.point.items():
                if mk in per:
                    z, v = _thin(per[mk][:, 2], per[mk][:, i])
                    _method_line(ax, z, v, meth)
        shown = [per[mk][:, j] for per in (data.point[m] for m in keep) for mk in per for j in (2, i)]
        truth = [T[:, j] for T in (data.truth or {}).values() for j in (2, i)]
        ax.xlim, ax.ylim = _limits(shown[::2] + truth[::2]), _limits(shown[1::2] + truth[1::2])
        ax.yinvert = i == 1
        ax.xlabel, ax.ylabel = "z (m)", ("x", "y")[i] + " (m)"
        ax.title = ("top view: x vs z", "side view: y vs z")[i]
    return fig, "Trajectories, top and side views" + _runaway_note(data, list(data.point))


def fig_error(data: ReportData) -> tuple[Figure, str] | None:
    """3-D error per frame (mean over markers), log scale, each method its colour."""
    if not any(data.errors.values()):
        return None
    fig = Figure(1200, 450, ident="error")
    ax = fig.axes[0]
    ax.ylog = True
    errs = {}
    for meth, per in data.errors.items():
        if e := list(per.values()):
            n = min(len(x) for x in e)
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                errs[meth] = np.nanmean([x[:n] for x in e], axis=0) * 1000
            _method_line(ax, *_envelope(errs[meth]), meth)
    shown = [errs[m][errs[m] > 0] for m in data.tracking() if m in errs]
    lim = _limits([np.log10(a) for a in shown], pad=0.05)
    if lim:
        ax.ylim = 10 ** lim[0], 10 ** lim[1]
    ax.xlabel, ax.ylabel = "frame", "3-D error (mm), mean over markers"
    return fig, "3-D error per frame" + _runaway_note(data, list(errs))


def fig_image_tracks(data: ReportData) -> tuple[Figure, str] | None:
    """Each camera's detections, one colour per marker (the marker's own)."""
    if not data.obs:
        return None
    n = len(data.cameras)
    cols = min(n, 2) if n <= 4 else 3
    rows = -(-n // cols)
    fig = Figure(1200, 450 * rows, rows, cols, "image_tracks")
    for c, ax in enumerate(fig.axes[:n]):
        for i, (mk, Y) in enumerate(sorted(data.obs.items())):
            u, v = _thin(Y[:, 2 * c], Y[:, 2 * c + 1])
            ax.dots(u, v, rgb_hex(marker_rgb(data.marker_colours, mk, i)), name=mk)
        ax.xlabel, ax.ylabel = "u (px)", "v (px)"
        ax.title = f"{data.cameras[c]} camera: detections (px)"
        ax.yinvert = True
        ax.equal_aspect()
    del fig.axes[n:]
    return fig, "Image-plane tracks (detections)"


def fig_target(data: ReportData) -> tuple[Figure, str] | None:
    """The four-point target's angle α and distance z over time: truth and each target method."""
    if not data.target:
        return None
    fig = Figure(1200, 450, 1, 2, "target")
    for ax, col, ylabel in ((fig.axes[0], "alpha", "α (mrad)"), (fig.axes[1], "distance", "z (mm)")):  # as the tables
        if data.target_truth is not None:
            _truth_line(ax, *_envelope(1000 * np.asarray(data.target_truth[col], dtype=float), data.target_truth["t"]))
        for meth, cols in data.target.items():
            _method_line(ax, *_envelope(1000 * np.asarray(cols[col], dtype=float), cols["t"]), meth)
        ax.xlabel, ax.ylabel, ax.title = "t (s)", ylabel, f"target {ylabel.split()[0]}"
    return fig, "Four-point target: α and z"


def fig_consistency(data: ReportData) -> tuple[Figure, str] | None:
    """NEES/3 and NIS/dof of each filter (moving mean over :data:`CONSISTENCY_WINDOW` frames, all
    markers) against the 95 % band of that mean: the quantities of the consistency table."""
    from pipeline.core.chi2 import chi2_quantile

    if not data.filters:
        return None
    w = CONSISTENCY_WINDOW
    fig = Figure(1200, 450, 1, 2, "consistency")
    for i, (ax, title, dof) in enumerate(((fig.axes[0], "NEES / 3, position, against truth", 3),
                                          (fig.axes[1], "NIS / dof of the filter's innovations", 4))):
        ax.ylog = True
        per_frame = []
        for meth, series in data.filters.items():
            v, ok = series[i], np.isfinite(series[i])
            if not ok.any():
                continue
            with np.errstate(all="ignore"):
                mean = np.convolve(np.where(ok, v, 0), np.ones(w), "same") / np.convolve(ok, np.ones(w), "same")
            _method_line(ax, *_envelope(mean), meth)
            per_frame.append(series[2])
        if per_frame:
            k = round(dof * w * float(np.median(per_frame)))  # χ² degrees of freedom in one moving mean
            ax.band(chi2_quantile(k, 0.025) / k, chi2_quantile(k, 0.975) / k, name="95 % band")  # no scipy import
        ax.xlabel, ax.ylabel, ax.title = "frame", f"moving mean over {w} frames", title
    return fig, "Filter consistency: NEES/3 and NIS/dof (1 when the covariance matches the errors)"


FIGURES: list[tuple[str, Callable]] = [("trajectories", fig_trajectories), ("error", fig_error),
                                       ("image_tracks", fig_image_tracks), ("target", fig_target),
                                       ("consistency", fig_consistency)]


def render_figures(data: ReportData, progress: Callable[[int, int], None] | None = None
                   ) -> list[tuple[str, str, str]]:
    """(name, caption, SVG text) of every figure the run has; ``progress`` gets (done, of)."""
    out = []
    if progress is not None:
        progress(0, len(FIGURES))
    for k, (name, make) in enumerate(FIGURES):
        if (made := make(data)) is not None:
            fig, caption = made
            out.append((name, caption, fig.svg()))
        if progress is not None:
            progress(k + 1, len(FIGURES))
    return out
