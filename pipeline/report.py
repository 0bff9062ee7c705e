"""``out/report.md``: the metrics table and matplotlib figures (trajectories in top and side views,
error vs frame per method, image-plane tracks per camera, filter consistency), built from the stage files alone so a
person who never opens rerun can read a run."""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.clip import Clip, load_detections, read_positions
from pipeline.errors import StereotrackError
from pipeline.io import atomic_path, read_csv, read_json_mapping, write_text
from pipeline.metrics import errors_per_frame
from pipeline.style import marker_rgb, method_colour, method_linestyle


def load_estimates(out_dir: Path) -> dict[str, dict[str, np.ndarray]]:
    """``estimates/<method>.csv`` → method → marker → positions (frames × 3)."""
    return {f.stem: read_positions(f)[0] for f in sorted((out_dir / "estimates").glob("[!.]*.csv"))}


def _hide_behind_camera(clip: Path, est: dict[str, dict[str, np.ndarray]], units: str | None
                        ) -> dict[str, dict[str, np.ndarray]]:
    """Estimates with points behind either camera set to NaN: they are counted in the metrics
    and the Checks section, never drawn as if they were metres in front of the rig."""
    from pipeline.camera import has_calibration, load_calibration

    if not has_calibration(clip):
        return est
    rig = load_calibration(clip, units)
    out: dict[str, dict[str, np.ndarray]] = {}
    for meth, per in est.items():
        out[meth] = {}
        for mk, P in per.items():
            P = P.copy()
            with np.errstate(invalid="ignore"):
                P[np.any(rig.depths(P) <= 0, axis=1)] = np.nan
            out[meth][mk] = P
    return out


def checks_section(metrics: dict) -> list[str]:
    """The report's "Checks" section: every input check, failed ones first."""
    checks = metrics.get("checks") or []
    if not checks:
        return []
    lines = ["## Checks", ""]
    failed = [c for c in checks if not c.get("ok")]
    lines.append(f"**{len(failed)} check(s) failed: look before trusting the numbers below.**" if failed
                 else "All input checks passed.")
    lines.append("")
    for c in sorted(checks, key=lambda c: bool(c.get("ok"))):
        lines.append(f"- {'✅' if c.get('ok') else '⚠️'} `{c.get('name')}`: {c.get('message')}")
    behind = {m: e.get("behind_camera") for m, e in metrics.get("methods", {}).items() if e.get("behind_camera")}
    if behind:
        lines.append("- estimates behind a camera (counted, not drawn): "
                     + ", ".join(f"{m} {n}" for m, n in behind.items()))
    return [*lines, ""]


def _save(fig, path: Path) -> None:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, bbox_inches="tight")


def _fmt(v) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "—"
    return f"{v:.4g}" if isinstance(v, float) else str(v)


def consistency_section(metrics: dict) -> list[str]:
    """Markdown: each filter's NEES (position, against truth) and NIS, normalized by their degrees
    of freedom (1 when the filter's covariance matches its errors) and the fraction of frames in
    the 95 % χ² band (0.95 when it does)."""
    rows = []
    for m, e in metrics.get("methods", {}).items():
        nees, nis = e.get("nees_position"), e.get("nis")
        if nees or nis:
            rows.append(f"| {m} | {_fmt(nees and nees['normalized_mean'])} | {_fmt(nees and nees['in_95'])} | "
                        f"{_fmt(nis and nis['normalized_mean'])} | {_fmt(nis and nis['in_95'])} |")
    if not rows:
        return []
    return ["## Filter consistency", "",
            "NEES/3 and NIS/dof average 1, and 95 % of frames fall inside the χ² band, when a filter's covariance "
            "matches its actual errors; far above 1 means over-confident, far below under-confident.", "",
            "| method | NEES/3 (position) | NEES in 95 % band | NIS/dof | NIS in 95 % band |", "|---|---|---|---|---|",
            *rows, ""]


def _consistency_figure(src: Path, figdir: Path, colour, plt) -> bool:
    """NEES and NIS per frame (moving mean over 15 frames, all markers) with the 95 % band of
    that mean; False when no method has them."""
    from pipeline.consistency import band

    series: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for f in sorted((src / "estimates").glob("[!.]*.csv")):
        cols = read_csv(f)
        if "nis" not in cols or not (np.isfinite(cols["nis"]).any() or np.isfinite(cols["nees"]).any()):
            continue
        frames = cols["frame"].astype(int)
        n = int(frames.max()) + 1
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            per = [np.bincount(frames, np.nan_to_num(v), n) / np.bincount(frames, np.isfinite(v), n)
                   for v in (cols["nees"], cols["nis"] / cols["nis_dof"])]
        series[f.stem] = (per[0], per[1])
    if not series:
        return False
    w = 15
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    # the band of a w-frame mean: χ²(3w)/w for NEES (3 dof), χ²(4w)/(4w) for NIS/dof (4 dof)
    bands = [np.array(band(3 * w)) / w, np.array(band(4 * w)) / (4 * w)]
    for ax, i, title in ((axes[0], 0, "NEES, position (3 dof), against truth"),
                         (axes[1], 1, "NIS / dof of the filter's innovations")):
        drawn = False
        for meth, vals in series.items():
            v = vals[i]
            if not np.isfinite(v).any():
                continue
            ok = np.isfinite(v)
            k = np.ones(w)
            with np.errstate(all="ignore"):
                mean = np.convolve(np.where(ok, v, 0), k, "same") / np.convolve(ok, k, "same")
            (ax.semilogy if i == 0 else ax.plot)(mean, color=colour(meth), lw=1, label=meth)
            drawn = True
        if drawn:
            ax.axhspan(*bands[i], color="0.85", zorder=0, label="95 % band")
        if i == 0:
            from matplotlib.ticker import ScalarFormatter

            ax.yaxis.set_major_formatter(ScalarFormatter())
            ax.yaxis.set_minor_formatter(ScalarFormatter())
        ax.set(xlabel="frame", ylabel=f"moving mean over {w} frames", title=title)
        ax.grid(alpha=0.3, which="both")
    _legend_outside(fig, axes)
    _save(fig, figdir / "consistency.png")
    plt.close(fig)
    return True


def metrics_table(metrics: dict) -> str:
    """Markdown table of the per-method metrics."""
    head = ("| method | 3-D RMSE (m) | mean (m) | median (m) | final (m) | reproj. RMSE (px) | α RMSE (rad) "
            "| z RMSE (m) | gated | steps/s |")
    lines = [head, "|" + "---|" * 10]
    for m, e in metrics.get("methods", {}).items():
        gated = "—" if e.get("gated") is None else f"{e['gated']}" + (f" ({e['restarts']} restarts)" if e.get("restarts")
                                                                     else "")
        lines.append(f"| {m} | {_fmt(e.get('rmse'))} | {_fmt(e.get('mean'))} | {_fmt(e.get('median'))} | "
                     f"{_fmt(e.get('final'))} | {_fmt(e.get('reprojection_rmse_px'))} | {_fmt(e.get('alpha_rmse_rad'))} | "
                     f"{_fmt(e.get('distance_rmse_m'))} | {gated} | {_fmt(e.get('steps_per_second'))} |")
    notes = [f"- **{m}**: {e['note']}" for m, e in metrics.get("methods", {}).items() if e.get("note")]
    return "\n".join(lines + (["", *notes] if notes else []))


def _legend_outside(fig, axes) -> None:
    """One legend for the figure, right of the axes (never over the data)."""
    handles: dict[str, object] = {}
    for ax in np.atleast_1d(axes):
        for h, lab in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(lab, h)
    if handles:
        fig.legend(list(handles.values()), list(handles), fontsize=8, loc="center left", bbox_to_anchor=(1.0, 0.5))
    fig.tight_layout()


def write_report(clip: str | Path | Clip, out_dir: str | Path | None = None,
                 progress: Callable[[int, int], None] | None = None, in_dir: str | Path | None = None) -> Path:
    """Write ``report.md`` and its figures into ``out_dir`` (default ``CLIP/out``) from the stage
    files in ``in_dir`` (default ``out_dir``); ``progress`` gets (figures done, figures in all)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    clip_ = Clip.open(clip)
    clip = clip_.folder
    out_dir = Path(out_dir) if out_dir else clip / "out"
    src = Path(in_dir) if in_dir else out_dir
    mpath = src / "metrics.json"
    if not mpath.is_file():
        raise StereotrackError("no metrics.json: run `stereotrack estimate` first", mpath)
    metrics = read_json_mapping(mpath, "metrics")
    est = load_estimates(src)
    truth = clip_.truth()
    est = _hide_behind_camera(clip, est, metrics.get("calibration_units"))
    obs = load_detections(src / "detections.csv") if (src / "detections.csv").is_file() else {}
    info = src / "detect.json"
    mcolours = read_json_mapping(info, "detect record").get("marker_colours", {}) if info.is_file() else {}
    total_figs = 5

    def done(k: int) -> None:
        if progress is not None:
            progress(k, total_figs)

    done(0)
    figdir = out_dir / "figures"
    markers = sorted({m for per in est.values() for m in per})
    figs = []

    fig, axes = plt.subplots(1, 2, figsize=(12, 5))
    for ax, (i, j, lab) in zip(axes, ((0, 2, "top view: x (m) vs z (m)"), (1, 2, "side view: y (m) vs z (m)")), strict=True):
        for mk in markers:
            if truth and mk in truth.positions:
                T = truth.positions[mk]
                ax.plot(T[:, j], T[:, i], "k-", lw=2.5, alpha=0.5, label="truth" if mk == markers[0] else None)
            for meth, per in est.items():
                if mk in per:
                    P = per[mk]
                    ax.plot(P[:, j], P[:, i], method_linestyle(meth), lw=1, color=method_colour(meth),
                            label=meth if mk == markers[0] else None)
        ax.set_xlabel("z (m)")
        ax.set_ylabel(lab.split(":")[1].split("vs")[0].strip())
        ax.set_title(lab)
        if i == 1:
            ax.invert_yaxis()
        ax.grid(alpha=0.3)
    _legend_outside(fig, axes)
    _save(fig, figdir / "trajectories.png")
    plt.close(fig)
    figs.append(("Trajectories (top and side views)", "figures/trajectories.png"))
    done(1)

    if truth is not None:
        fig, ax = plt.subplots(figsize=(12, 4.5))
        for meth, per in est.items():
            errs = [errors_per_frame(per[mk], truth.positions[mk]) for mk in per if mk in truth.positions]
            if errs:
                n = min(len(e) for e in errs)
                with np.errstate(all="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    mean_err = np.nanmean([e[:n] for e in errs], axis=0)
                ax.semilogy(mean_err, method_linestyle(meth), color=method_colour(meth), label=meth)
        ax.set_xlabel("frame")
        ax.set_ylabel("3-D error (m), mean over markers")
        ax.grid(alpha=0.3, which="both")
        _legend_outside(fig, ax)
        _save(fig, figdir / "error.png")
        plt.close(fig)
        figs.append(("3-D error per frame", "figures/error.png"))
    done(2)

    if obs:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
        for c, ax in enumerate(axes):
            for i, (mk, Y) in enumerate(sorted(obs.items())):
                ax.plot(Y[:, 2 * c], Y[:, 2 * c + 1], ".", ms=2, color=np.array(marker_rgb(mcolours, mk, i)) / 255,
                        label=mk)
            ax.set_title(("left", "right")[c] + " camera: detections (px)")
            ax.invert_yaxis()
            ax.set_aspect("equal", adjustable="datalim")
            ax.grid(alpha=0.3)
        for ax in axes:
            ax.set(xlabel="u (px)", ylabel="v (px)")
        _legend_outside(fig, axes)
        _save(fig, figdir / "image_tracks.png")
        plt.close(fig)
        figs.append(("Image-plane tracks", "figures/image_tracks.png"))
    done(3)

    target_csvs = [f for f in sorted((src / "estimates").glob("[!.]*.csv"))
                   if "alpha" in (f.read_text().split("\n", 1)[0].split(","))]
    if target_csvs:
        fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
        if (clip / "target_truth.csv").is_file():
            tt = read_csv(clip / "target_truth.csv")
            axes[0].plot(tt["t"], tt["alpha"], "k-", lw=2.5, alpha=0.5, label="truth")
            axes[1].plot(tt["t"], tt["distance"], "k-", lw=2.5, alpha=0.5, label="truth")
        for f in target_csvs:
            cols = read_csv(f)
            col, ls = method_colour(f.stem), method_linestyle(f.stem)
            axes[0].plot(cols["t"], cols["alpha"], ls, color=col, lw=1, label=f.stem)
            axes[1].plot(cols["t"], cols["distance"], ls, color=col, lw=1, label=f.stem)
        axes[0].set(xlabel="t (s)", ylabel="α (rad)", title="target angle α")
        axes[1].set(xlabel="t (s)", ylabel="z (m)", title="target distance z")
        for ax in axes:
            ax.grid(alpha=0.3)
        _legend_outside(fig, axes)
        _save(fig, figdir / "target.png")
        plt.close(fig)
        figs.append(("Four-point target: α and z", "figures/target.png"))
    done(4)

    if _consistency_figure(src, figdir, method_colour, plt):
        figs.append(("Filter consistency: NEES and NIS", "figures/consistency.png"))
    done(5)

    lines = [f"# stereotrack report: {clip.name}", "",
             f"{metrics.get('frames', '?')} frames, dt = {metrics.get('dt', float('nan')):.4g} s; "
             + ("errors against the rendered ground truth." if metrics.get("has_truth") else "no ground truth (real footage)."),
             "", *checks_section(metrics), "## Metrics", "", metrics_table(metrics), "", *consistency_section(metrics)]
    for title, rel in figs:
        lines += [f"## {title}", "", f"![{title}]({rel})", ""]
    path = out_dir / "report.md"
    write_text(path, "\n".join(lines))
    return path
