"""``out/report.md`` and the self-contained ``out/report.html``: the run's tables (errors in
millimetres, each column's best value marked), its input checks, and matplotlib figures
(trajectories, error per frame, image-plane tracks, the target's α and z, filter consistency),
built from the stage files so a person who never opens rerun can read a run.

Only the methods of this run's ``metrics.json`` are drawn (estimate CSVs left by earlier runs are
not); axes are set by the methods that track, and a method that runs away (3-D RMSE, or without
truth reprojection RMSE, over :data:`RUNAWAY` × the run's median) is clipped and named."""

from __future__ import annotations

import io
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.clip import Clip, load_detections, positions_from_columns
from pipeline.core.errors import StereotrackError
from pipeline.core.io import check_frame_column, read_csv, read_json_mapping, write_bytes, write_text
from pipeline.core.outputs import Outputs
from pipeline.evaluation.metrics import RUNAWAY, runaways
from pipeline.evaluation.scores import FrameScores, errors_per_frame
from pipeline.present import html as H
from pipeline.present.style import TRUTH_STYLE, marker_rgb, method_colour, method_hex, method_linestyle
from pipeline.present.tables import Column, Table, inline, number, to_html, to_markdown

if TYPE_CHECKING:
    from pipeline.estimate import EstimateResult
    from pipeline.estimators import Track

#: figure resolution: sharp on a laptop screen, cheap to encode
DPI = 100
#: frames in the moving mean of the consistency figure
CONSISTENCY_WINDOW = 15


@dataclass
class ReportData:
    """What the report draws, read once from the stage files."""
    name: str
    out_dir: Path
    metrics: dict
    point: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # method → marker → positions
    target: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # method → CSV columns
    filters: dict[str, tuple[np.ndarray, np.ndarray, float]] = field(default_factory=dict)  # NEES/3, NIS/dof, n
    truth: dict[str, np.ndarray] | None = None
    target_truth: dict[str, np.ndarray] | None = None
    obs: dict[str, np.ndarray] = field(default_factory=dict)
    marker_colours: dict[str, list[int]] = field(default_factory=dict)

    @property
    def runaways(self) -> list[str]:
        return runaways(self.metrics)

    def add_method(self, est: EstimateResult, m: str, per: dict[str, Track], scores: dict[str, FrameScores]) -> None:
        """A point method's positions (behind-camera points hidden, on a copy) and its filter
        series, from its tracks and their scores in memory."""
        self.point[m] = {mk: t.position.copy() for mk, t in per.items()}
        _hide_behind(est.rig, {m: self.point[m]})
        if (s := _track_filter_series(scores)) is not None:
            self.filters[m] = s

    def tracking(self) -> list[str]:
        """Point methods that are drawn to scale (not runaways)."""
        return [m for m in self.point if m not in self.runaways]


def _hide_behind(rig: StereoRig, est: dict[str, dict[str, np.ndarray]]) -> None:
    """Points behind either camera set to NaN: counted in the metrics and the Checks section,
    never drawn as if they were metres in front of the rig."""
    for per in est.values():
        for P in per.values():
            with np.errstate(invalid="ignore"):
                P[np.any(rig.depths(P) <= 0, axis=1)] = np.nan


def _filter_series(cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A filter's NEES/3 and NIS/dof per frame (mean over markers) and markers per frame."""
    if not {"nis", "nis_dof", "nees"} <= set(cols) or not (np.isfinite(cols["nis"]).any()
                                                           or np.isfinite(cols["nees"]).any()):
        return None
    frames = cols["frame"].astype(int)
    n = int(frames.max()) + 1
    with np.errstate(all="ignore"):
        per = [np.bincount(frames, np.nan_to_num(v), n) / np.bincount(frames, np.isfinite(v), n)
               for v in (cols["nees"] / 3, cols["nis"] / cols["nis_dof"])]
    return per[0], per[1], max(1.0, len(frames) / n)


def load_report_data(clip: Clip, src: Path, out_dir: Path) -> ReportData:
    """The run's metrics and, for its methods only, their estimate CSVs (each read once), with
    truth, detections and the marker colours the detect stage recorded."""
    src_out = Outputs(src)
    mpath = src_out.metrics
    if not mpath.is_file():
        raise StereotrackError("no metrics.json: run `stereotrack estimate` first", mpath)
    metrics = read_json_mapping(mpath, "metrics")
    data = ReportData(clip.folder.name, out_dir, metrics)
    for m, entry in metrics.get("methods", {}).items():
        path = src_out.estimates(m)
        if not path.is_file():
            continue
        if entry.get("target"):
            data.target[m] = read_csv(path, ["t", "alpha", "distance"], numeric=["t", "alpha", "distance"])
            continue
        cols = read_csv(path, ["frame", "marker", "x", "y", "z"], numeric=["x", "y", "z"], finite=["frame"])
        check_frame_column(cols["frame"], None, path)
        data.point[m] = positions_from_columns(cols)[0]
        if (s := _filter_series(cols)) is not None:
            data.filters[m] = s
    if data.point and clip.has_calibration:
        _hide_behind(clip.rig(metrics.get("calibration_units")), data.point)
    truth = clip.truth()
    data.truth = truth.positions if truth is not None else None
    if (clip.folder / "target_truth.csv").is_file() and data.target:
        data.target_truth = read_csv(clip.folder / "target_truth.csv", ["t", "alpha", "distance"],
                                     numeric=["t", "alpha", "distance"])
    if src_out.detections.is_file():
        data.obs = load_detections(src_out.detections)
    if src_out.detect_info.is_file():
        data.marker_colours = read_json_mapping(src_out.detect_info, "detect record").get("marker_colours", {})
    return data


def _track_filter_series(scores: dict[str, FrameScores]) -> tuple[np.ndarray, np.ndarray, float] | None:
    """A filter's NEES/3 and NIS/dof per frame from its tracks' scores in memory: the columns its
    estimates CSV holds, through :func:`_filter_series`."""
    cols = [s.columns() for s in scores.values()]
    c = np.vstack(cols)
    return _filter_series({"frame": np.concatenate([np.arange(len(x)) for x in cols]), "nis": c[:, 0],
                           "nis_dof": c[:, 1], "nees": c[:, 2]})


def report_data(clip: Clip, est: EstimateResult, marker_colours: dict[str, list[int]], out_dir: Path,
                data: ReportData | None = None) -> ReportData:
    """The report's data from a run's results in memory: what :func:`load_report_data` would read
    back from the stage files, read from nothing (the calibration included). ``data``: what
    :meth:`ReportData.add_method` already took of methods whose tracks were not kept."""
    data = data or ReportData(clip.folder.name, out_dir, {})
    data.name, data.out_dir, data.metrics = clip.folder.name, out_dir, est.metrics
    data.truth = est.truth_positions
    data.obs, data.marker_colours = dict(est.observations), dict(marker_colours)
    for m, per in est.tracks.items():
        if m not in data.point:
            data.add_method(est, m, per, est.scores[m])
    for m, t in est.target_tracks.items():
        data.target[m] = {"t": np.arange(len(t.position)) * est.dt, "alpha": t.extra["alpha"],
                          "distance": t.extra["distance"]}
    tg = est.target
    if tg is not None and tg.alpha is not None and tg.distance is not None and est.target_tracks:
        data.target_truth = {"t": np.arange(len(tg.alpha)) * est.dt, "alpha": tg.alpha, "distance": tg.distance}
    return data


# ---------------------------------------------------------------- figures


def _legend(fig, axes) -> None:
    """One legend for the figure, right of the axes (never over the data), listing every series."""
    handles: dict[str, object] = {}
    for ax in np.atleast_1d(axes):
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    fig.tight_layout(rect=(0, 0, 0.84 if handles else 1, 1))
    if handles:
        fig.legend(list(handles.values()), list(handles), fontsize=8, loc="center left", bbox_to_anchor=(0.845, 0.5),
                   ncol=2 if len(handles) > 16 else 1)


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
    markers = sorted({mk for per in data.point.values() for mk in per})
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
    if data.truth is None or not data.point:
        return None
    fig, ax = plt.subplots(figsize=(12, 4.5))
    errs = {}
    for meth, per in data.point.items():
        e = [errors_per_frame(per[mk], data.truth[mk]) for mk in per if mk in data.truth]
        if e:
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
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    for c, ax in enumerate(axes):
        for i, (mk, Y) in enumerate(sorted(data.obs.items())):
            ax.plot(*_thin(Y[:, 2 * c], Y[:, 2 * c + 1]), ".", ms=2, label=mk,
                    color=np.array(marker_rgb(data.marker_colours, mk, i)) / 255)
        ax.set(xlabel="u (px)", ylabel="v (px)", title=("left", "right")[c] + " camera: detections (px)")
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
    for ax, col, ylabel in ((axes[0], "alpha", "α (rad)"), (axes[1], "distance", "z (m)")):
        if data.target_truth is not None:
            ax.plot(*_envelope(data.target_truth[col], data.target_truth["t"]), label="truth", **TRUTH_STYLE)
        for meth, cols in data.target.items():
            ax.plot(*_envelope(cols[col], cols["t"]), method_linestyle(meth), color=method_colour(meth), lw=1,
                    label=meth)
        ax.set(xlabel="t (s)", ylabel=ylabel, title=f"target {ylabel.split()[0]}")
        ax.grid(alpha=0.3)
    _legend(fig, axes)
    return fig, "Four-point target: α and z"


def fig_consistency(data: ReportData, plt) -> tuple[object, str] | None:
    """NEES/3 and NIS/dof of each filter (moving mean over :data:`CONSISTENCY_WINDOW` frames, all
    markers) against the 95 % band of that mean: the quantities of the consistency table."""
    from pipeline.evaluation.consistency import band

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
            ax.axhspan(*(np.array(band(k)) / k), color="0.85", zorder=0, label="95 % band")
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


def render_figures(data: ReportData, progress: Callable[[int, int], None] | None = None
                   ) -> list[tuple[str, str, bytes]]:
    """(name, caption, PNG bytes) of every figure the run has; ``progress`` gets (done, of)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = []
    for k, (name, make) in enumerate(FIGURES):
        if progress is not None:
            progress(k, len(FIGURES))
        made = make(data, plt)
        if made is None:
            continue
        fig, caption = made
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=DPI)
        plt.close(fig)
        _release_lines(fig)
        out.append((name, caption, buf.getvalue()))
    if progress is not None:
        progress(len(FIGURES), len(FIGURES))
    return out


# ---------------------------------------------------------------- tables


def _col(methods: dict, title: str, key: str, fmt, best=None, sub: str | None = None) -> Column:
    vals = [(e.get(key) or {}).get(sub) if sub else e.get(key) for e in methods.values()]
    return Column(title, vals, fmt, best)


def _keep(cols: list[Column]) -> list[Column]:
    """Columns that hold at least one value."""
    return [c for c in cols if any(v is not None and not (isinstance(v, float) and np.isnan(v)) for v in c.values)]


def point_table(metrics: dict) -> Table | None:
    """Per point method: errors against truth (mm), reprojection (px), gate counts, speed."""
    ms = {m: e for m, e in metrics.get("methods", {}).items() if not e.get("target")}
    if not ms:
        return None
    mm, px = number(".2f", 1000), number(".2f")
    cols = _keep([_col(ms, "3-D RMSE (mm)", "rmse", mm, "min"), _col(ms, "mean (mm)", "mean", mm, "min"),
                  _col(ms, "median (mm)", "median", mm, "min"), _col(ms, "final (mm)", "final", mm, "min"),
                  _col(ms, "reproj. RMSE (px)", "reprojection_rmse_px", px, "min"),
                  _col(ms, "gated", "gated", number("d")), _col(ms, "restarts", "restarts", number("d")),
                  _col(ms, "steps/s", "steps_per_second", number(",.0f"), "max")])
    notes = [f"**{m}**: {e['note']}" for m, e in ms.items() if e.get("note")]
    notes += [f"**{m}** runs away (over {RUNAWAY:g}× the run's median error): clipped in the figures"
              for m in runaways(metrics)]
    return Table("method", list(ms), cols, notes)


def target_table(metrics: dict) -> Table | None:
    """Per four-point target method: α (mrad) and distance (mm) errors, valid frames, speed."""
    ms = {m: e for m, e in metrics.get("methods", {}).items() if e.get("target")}
    if not ms:
        return None
    cols = _keep([_col(ms, "α RMSE (mrad)", "alpha_rmse_rad", number(".2f", 1000), "min"),
                  _col(ms, "z RMSE (mm)", "distance_rmse_m", number(".2f", 1000), "min"),
                  _col(ms, "valid frames", "valid_frames", number("d"), "max"), _col(ms, "gated", "gated", number("d")),
                  _col(ms, "steps/s", "steps_per_second", number(",.0f"), "max")])
    return Table("target method", list(ms), cols)


def consistency_table(metrics: dict) -> Table | None:
    """Per filter: NEES/3 and NIS/dof (1 when consistent) and the share of frames in the 95 % band."""
    ms = {m: e for m, e in metrics.get("methods", {}).items() if e.get("nees_position") or e.get("nis")}
    if not ms:
        return None
    ratio, share = number(".2f"), number(".0f", 100, " %")
    cols = _keep([_col(ms, "NEES/3", "nees_position", ratio, 1.0, "normalized_mean"),
                  _col(ms, "NEES in 95 % band", "nees_position", share, 0.95, "in_95"),
                  _col(ms, "NIS/dof", "nis", ratio, 1.0, "normalized_mean"),
                  _col(ms, "NIS in 95 % band", "nis", share, 0.95, "in_95")])
    return Table("filter", list(ms), cols)


TABLE_INTRO = {
    "consistency": "NEES/3 and NIS/dof average 1, and 95 % of frames fall inside the χ² band, when a filter's "
                   "covariance matches its actual errors; far above 1 means over-confident, far below under-confident.",
    "metrics": "Best value per column in bold. steps/s is wall-clock speed on this machine and varies with its load; "
               "compare methods within one run.",
}


def tables(metrics: dict) -> list[tuple[str, str, Table]]:
    """(section title, intro, table) of every table the run has."""
    out = []
    for title, intro, t in (("Metrics", TABLE_INTRO["metrics"], point_table(metrics)),
                            ("Four-point target", "", target_table(metrics)),
                            ("Filter consistency", TABLE_INTRO["consistency"], consistency_table(metrics))):
        if t is not None:
            out.append((title, intro, t))
    return out


# ---------------------------------------------------------------- pages


def check_lines(metrics: dict) -> tuple[int, list[tuple[bool, str]]]:
    """(failed checks, (passed, Markdown line) per check, failed first)."""
    checks = metrics.get("checks") or []
    failed = [c for c in checks if not c.get("ok")]
    lines = [(bool(c.get("ok")), f"`{c.get('name')}`: {c.get('message')}")
             for c in sorted(checks, key=lambda c: bool(c.get("ok")))]
    behind = {m: e["behind_camera"] for m, e in metrics.get("methods", {}).items() if e.get("behind_camera")}
    if behind:
        lines.append((False, "estimates behind a camera (counted, not drawn): "
                      + ", ".join(f"{m} {n}" for m, n in behind.items())))
    return len(failed), lines


def checks_section(metrics: dict) -> list[str]:
    """The report's "Checks" section: every input check, failed ones first."""
    if not metrics.get("checks"):
        return []
    failed, lines = check_lines(metrics)
    head = (f"**{failed} check(s) failed: look before trusting the numbers below.**" if failed
            else "All input checks passed.")
    return ["## Checks", "", head, "", *[f"- {'✅' if ok else '⚠️'} {x}" for ok, x in lines], ""]


def _summary_line(metrics: dict) -> str:
    return (f"{metrics.get('frames', '?')} frames, dt = {metrics.get('dt', float('nan')):.4g} s; "
            + ("errors against the rendered ground truth." if metrics.get("has_truth")
               else "no ground truth (real footage)."))


def markdown_report(data: ReportData, figures: list[tuple[str, str, str]], replay: str) -> str:
    """report.md: checks, tables, then figures (name, caption, relative path)."""
    lines = [f"# stereotrack report: {data.name}", "", _summary_line(data.metrics), "",
             f"Replay the run: `{replay}`", "", *checks_section(data.metrics)]
    for title, intro, t in tables(data.metrics):
        lines += [f"## {title}", "", *([intro, ""] if intro else []), to_markdown(t), ""]
    for _, caption, rel in figures:
        head, _, rest = caption.partition("; ")
        lines += [f"## {head}", "", f"![{head}]({rel})", "", *([f"*{rest[0].upper()}{rest[1:]}.*", ""] if rest else [])]
    return "\n".join(lines)


def html_report(data: ReportData, figures: list[tuple[str, str, bytes]], replay: str) -> str:
    """report.html: the same content with figures embedded and a legend of method colours."""
    failed, checks = check_lines(data.metrics)
    body = [f"<h1>stereotrack report: {inline(data.name)}</h1><p>{inline(_summary_line(data.metrics))}</p>",
            f"<p>Replay the run in rerun: <code>{inline(replay)}</code></p>"]
    if checks:
        head = f"{failed} check(s) failed: look before trusting the numbers below." if failed else "All input checks passed."
        body.append(f"<div class='checks{' failed' if failed else ''}'><b>Checks: {head}</b><ul>"
                    + "".join(f"<li class={'pass' if ok else 'fail'}>{inline(x)}</li>" for ok, x in checks)
                    + "</ul></div>")
    body.append("<p>" + " &nbsp; ".join(H.swatch(method_hex(m), m) for m in data.metrics.get("methods", {}))
                + " &nbsp; <span class=swatch style='background:#000;opacity:.55'></span>truth (dashed)</p>")
    for title, intro, t in tables(data.metrics):
        body += [f"<h2>{title}</h2>", f"<p class=note>{inline(intro)}</p>" if intro else "", to_html(t)]
    if figures:
        body.append("<h2>Figures</h2>")
    body += [H.figure(png, caption) for _, caption, png in figures]
    if not figures:
        body.append("<p class=note>No figures (a batch draws them with <code>--figures</code>).</p>")
    return H.page(f"stereotrack report: {data.name}", body)


def write_report(clip: str | Path | Clip, out_dir: str | Path | None = None,
                 progress: Callable[[int, int], None] | None = None, in_dir: str | Path | None = None,
                 figures: bool = True, data: ReportData | None = None) -> Path:
    """Write ``report.md``, ``report.html`` and (with ``figures``) ``figures/*.png`` into
    ``out_dir`` (default ``CLIP/out``) from ``data`` (a run's results in memory, see
    :func:`report_data`), else from the stage files in ``in_dir`` (default ``out_dir``);
    ``progress`` gets (figures done, figures in all). Returns report.md's path."""
    clip_ = Clip.open(clip)
    out = Outputs.of(clip_.folder, out_dir)
    out_dir = out.folder
    if data is None:
        data = load_report_data(clip_, Path(in_dir) if in_dir else out_dir, out_dir)
    figs = render_figures(data, progress) if figures else []
    for name, _, png in figs:
        write_bytes(out.figure(name), png)
    replay = f"stereotrack view {out_dir}"
    write_text(out.report_html, html_report(data, figs, replay))
    path = out.report_md
    write_text(path, markdown_report(data, [(n, c, out.figure(n).relative_to(out_dir).as_posix()) for n, c, _ in figs],
                                     replay))
    return path
