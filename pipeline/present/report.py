"""``out/report.md`` and the self-contained ``out/report.html``: the run's tables (errors in
millimetres, each column's best value marked), its input checks, and SVG figures
(trajectories, error per frame, image-plane tracks, the target's α and z, filter consistency),
built from the stage files so a person who never opens rerun can read a run.

Only the methods of this run's ``metrics.json`` are drawn (estimate CSVs left by earlier runs are
not); axes are set by the methods that track, and a method that runs away (3-D RMSE, or without
truth reprojection RMSE, over :data:`RUNAWAY` × the run's median) is clipped and named."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.core.clip import Clip
from pipeline.core.io import write_text
from pipeline.core.outputs import Outputs, final_folder
from pipeline.evaluation.metrics import RUNAWAY, runaways
from pipeline.present import html as H
from pipeline.present.figures import render_figures
from pipeline.present.report_data import ReportData, load_report_data
from pipeline.present.style import method_hex
from pipeline.present.tables import Column, Table, inline, number, to_html, to_markdown

if TYPE_CHECKING:
    pass

# ---------------------------------------------------------------- tables


def _col(methods: dict, title: str, key: str, fmt, best=None, sub: str | None = None,
         good: tuple[float, float] | None = None) -> Column:
    vals = [(e.get(key) or {}).get(sub) if sub else e.get(key) for e in methods.values()]
    return Column(title, vals, fmt, best, good)


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
    # a cell is marked only where the filter is consistent there: mean within 0.5–2, 80 % in the band
    mean_ok, band_ok = (0.5, 2.0), (0.8, 1.0)
    cols = _keep([_col(ms, "NEES/3", "nees_position", ratio, 1.0, "normalized_mean", mean_ok),
                  _col(ms, "NEES in 95 % band", "nees_position", share, 0.95, "in_95", band_ok),
                  _col(ms, "NIS/dof", "nis", ratio, 1.0, "normalized_mean", mean_ok),
                  _col(ms, "NIS in 95 % band", "nis", share, 0.95, "in_95", band_ok)])
    return Table("filter", list(ms), cols)


def identity_tables(metrics: dict) -> list[tuple[str, str, Table]]:
    """Per group of identical markers, per point method: the identity metrics against the truth."""
    ms = {m: e["identity"] for m, e in metrics.get("methods", {}).items() if e.get("identity")}
    groups = sorted({g for ident in ms.values() for g, v in ident.items() if v})
    out = []
    for g in groups:
        per = {m: ident[g] for m, ident in ms.items() if ident.get(g)}
        share, d = number(".3f"), number("d")
        cols = _keep([_col(per, "IDF1", "idf1", share, "max"), _col(per, "HOTA", "hota", share, "max"),
                      _col(per, "DetA", "deta", share, "max"), _col(per, "AssA", "assa", share, "max"),
                      _col(per, "MOTA", "mota", share, "max"), _col(per, "ID switches", "id_switches", d, "min"),
                      _col(per, "fragmentations", "fragmentations", d, "min"),
                      _col(per, "MOTP (mm)", "motp_m", number(".1f", 1000), "min"),
                      _col(per, "GOSPA (mm)", "gospa_m", number(".1f", 1000), "min")])
        threshold = next(iter(per.values())).get("threshold_m", float("nan"))
        intro = (f"Tracks of the group `{g}` against its markers' truth: a track matches a marker within "
                 f"{1000 * threshold:.0f} mm (CLEAR MOT, IDF1), HOTA's similarity falls to 0 at that distance, "
                 f"GOSPA (p = 2) cuts off there.")
        out.append((f"Identity: {g}", intro, Table("method", list(per), cols)))
    return out


TABLE_INTRO = {
    "consistency": "NEES/3 and NIS/dof average 1, and 95 % of frames fall inside the χ² band, when a filter's "
                   "covariance matches its actual errors; far above 1 means over-confident, far below under-confident. "
                   "A cell is marked best only where that filter is consistent (mean 0.5–2, 80 % in the band).",
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
    return out + identity_tables(metrics)


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
    return len(failed) + bool(behind), lines  # a failed line is a failed check: never "all passed" above it


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


def html_report(data: ReportData, figures: list[tuple[str, str, str]], replay: str) -> str:
    """report.html: the same content with figures embedded and a legend of method colours."""
    failed, checks = check_lines(data.metrics)
    body = [f"<h1>stereotrack report: {inline(data.name)}</h1><p>{inline(_summary_line(data.metrics))}</p>",
            f"<p>Replay the run in rerun: <code>{inline(replay)}</code></p>"]
    if checks:
        head = f"{failed} check(s) failed: look before trusting the numbers below." if failed else "All input checks passed."
        body.append(f"<div class='checks{' failed' if failed else ''}'><b>Checks: {head}</b><ul>"
                    + "".join(f"<li class={'pass' if ok else 'fail'}>{inline(x)}</li>" for ok, x in checks)
                    + "</ul></div>")
    truth_key = " &nbsp; <span class=swatch style='background:#000;opacity:.55'></span>truth (dashed)"
    body.append("<p>" + " &nbsp; ".join(H.swatch(method_hex(m), m) for m in data.metrics.get("methods", {}))
                + (truth_key if data.metrics.get("has_truth") else "") + "</p>")  # no truth, no key for it
    for title, intro, t in tables(data.metrics):
        body += [f"<h2>{title}</h2>", f"<p class=note>{inline(intro)}</p>" if intro else "", to_html(t)]
    if figures:
        body.append("<h2>Figures</h2>")
    body += [H.figure(svg, caption) for _, caption, svg in figures]
    if not figures:
        body.append("<p class=note>No figures (a batch draws them with <code>--figures</code>).</p>")
    return H.page(f"stereotrack report: {data.name}", body)


def write_report(clip: str | Path | Clip, out_dir: str | Path | None = None,
                 progress: Callable[[int, int], None] | None = None, in_dir: str | Path | None = None,
                 figures: bool = True, data: ReportData | None = None) -> Path:
    """Write ``report.md``, ``report.html`` and (with ``figures``) ``figures/*.svg`` into
    ``out_dir`` (default ``CLIP/out``) from ``data`` (a run's results in memory, see
    :func:`report_data`), else from the stage files in ``in_dir`` (default ``out_dir``);
    ``progress`` gets (figures done, figures in all). Returns report.md's path."""
    clip_ = Clip.open(clip)
    out = Outputs.of(clip_.folder, out_dir)
    out_dir = out.folder
    if data is None:
        data = load_report_data(clip_, Path(in_dir) if in_dir else out_dir, out_dir)
    figs = render_figures(data, progress) if figures else []
    for name, _, svg in figs:
        write_text(out.figure(name), svg)
    replay = f"stereotrack view {final_folder(out_dir)}"  # a batch's clip: where it will be, not its attempt
    write_text(out.report_html, html_report(data, figs, replay))
    path = out.report_md
    write_text(path, markdown_report(data, [(n, c, out.figure(n).relative_to(out_dir).as_posix()) for n, c, _ in figs],
                                     replay))
    return path
