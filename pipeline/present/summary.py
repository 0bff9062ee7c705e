"""A batch's summary: the per-method leaderboard (mean and median 3-D RMSE across clips with 95 %
confidence intervals, runaways, failures, speed) and the per-clip table, written as
``summary.html`` (self-contained, linking each clip's report), ``summary.md``, ``summary.csv``
(one row per clip and method) and ``summary_methods.csv`` (one row per method)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.core.io import Schema, write_csv, write_text
from pipeline.core.outputs import REPORT_HTML, Outputs
from pipeline.evaluation.metrics import runaways
from pipeline.present import html as H
from pipeline.present.style import method_hex
from pipeline.present.tables import Column, Table, inline, number, to_html, to_markdown

SUMMARY = Schema("OUT/summary.csv", "one clip and method (a clip with no method scored has one row)", "batch", {
    "clip": "the clip's folder name",
    "status": "ok, failed, or skipped (complete from an earlier batch, its manifest verified)",
    "method": "the method",
    "rmse_m": "3-D RMSE against the truth, m (empty without truth)",
    "final_m": "3-D error at the last frame, m",
    "reprojection_rmse_px": "RMSE of the estimates reprojected into both cameras against the detections, px",
    "steps_per_second": "the method's estimation speed on this clip (wall clock), steps/s",
    "attempts": "attempts made (more than 1 where a worker died under an attempt)",
    "error": "why the clip failed (one line), else empty",
})
METHODS_SUMMARY = Schema("OUT/summary_methods.csv", "one method across the batch's clips", "batch", {
    "method": "the method",
    "clips": "clips that scored it",
    "mean_rmse_m": "mean of its 3-D RMSE over those clips, m",
    "mean_ci_low_m": "Student-t 95 % interval for that mean (lower end clipped at 0), m",
    "mean_ci_high_m": "Student-t 95 % interval for that mean (lower end clipped at 0), m",
    "median_rmse_m": "median of its 3-D RMSE over the clips, m",
    "median_ci_low_m": "distribution-free 95 % interval for the median (binomial order statistics; none below 6 "
                       "clips), m",
    "median_ci_high_m": "distribution-free 95 % interval for the median (binomial order statistics; none below 6 "
                        "clips), m",
    "runaways": "clips where its error was over 10× that clip's median",
    "failures": "clips where it scored nothing (no estimate, or the clip failed)",
    "median_steps_per_second": "its median speed over the clips, steps/s",
    "median_reprojection_px": "median over the clips of its estimates' reprojection RMSE against the detections, px "
                              "(no truth needed)",
    "median_nis_mean": "median over the clips of its normalised innovation squared over the degrees of freedom "
                       "(a consistent filter: 1; filters only, no truth needed)",
    "median_nis_in_95": "median over the clips of the share of frames whose NIS lies in the 95 % χ² band (filters)",
    "restarts": "restarts over the clips (a track gated too long, or back from a gap, began again)",
    "paired_clips": "clips where both it and the best method (lowest mean 3-D RMSE) scored",
    "paired_diff_m": "mean over those clips of its 3-D RMSE minus the best method's, m (clips share difficulty: "
                     "the paired difference separates methods whose intervals across clips overlap)",
    "paired_diff_ci_low_m": "Student-t 95 % interval for that paired mean difference, m",
    "paired_diff_ci_high_m": "Student-t 95 % interval for that paired mean difference, m",
})
SUMMARY_COLUMNS, METHOD_COLUMNS = SUMMARY.names, METHODS_SUMMARY.names


@dataclass
class ClipOutcome:
    clip: str
    status: str  # "ok", "failed", "skipped" (complete from an earlier batch, manifest verified)
    metrics: dict = field(default_factory=dict)
    error: str = ""
    warnings: list[str] = field(default_factory=list)
    #: attempts made: 1, more when a worker died under an attempt and Dask ran the clip again; an
    #: outcome that no attempt finished starts at 0 and counts the attempts whose worker died
    attempts: int = 1


def clip_warnings(o: ClipOutcome) -> list[str]:
    """A clip's warnings: those raised while processing it, else its failed input checks."""
    if o.warnings:
        return o.warnings
    return [c.get("message", "") for c in (o.metrics or {}).get("checks", []) if not c.get("ok")]


def mean_ci(x: np.ndarray, level: float = 0.95, clip: bool = True) -> tuple[float, float]:
    """Student-t interval for the mean of ``x`` (NaNs when fewer than two values), its lower end
    clipped at 0 unless ``clip`` is False (errors are never negative; few, skewed clips can put
    the t interval below; a difference of errors can be)."""
    from scipy import stats

    if len(x) < 2:
        return math.nan, math.nan
    half = stats.t.ppf(0.5 + level / 2, len(x) - 1) * np.std(x, ddof=1) / math.sqrt(len(x))
    lo = float(np.mean(x) - half)
    return (max(0.0, lo) if clip else lo), float(np.mean(x) + half)


def median_ci(x: np.ndarray, level: float = 0.95) -> tuple[float, float]:
    """Distribution-free interval for the median: the order statistics whose ranks the binomial
    (n, ½) puts around the middle with at least ``level`` coverage (NaNs when n < 6, where even
    the extremes cover less than 95 %)."""
    from scipy import stats

    n, q = len(x), (1 - level) / 2
    if n == 0:
        return math.nan, math.nan
    k = int(stats.binom.ppf(q, n, 0.5))
    r = k if stats.binom.cdf(k, n, 0.5) > q else k + 1  # the largest r with P(Bin ≤ r − 1) ≤ q
    if r < 1:
        return math.nan, math.nan
    s = np.sort(x)
    return float(s[r - 1]), float(s[n - r])


@dataclass
class MethodRow:
    """One method across the batch's clips."""
    method: str
    rmse: list[float] = field(default_factory=list)
    by_clip: dict[str, float] = field(default_factory=dict)  # the same RMSEs, by clip (to pair methods)
    speed: list[float] = field(default_factory=list)
    runaways: int = 0
    failures: int = 0
    reprojection: list[float] = field(default_factory=list)
    nis_mean: list[float] = field(default_factory=list)
    nis_in_95: list[float] = field(default_factory=list)
    restarts: int = 0

    def values(self) -> dict[str, Any]:
        x = np.array(self.rmse)
        lo, hi = mean_ci(x)
        mlo, mhi = median_ci(x)
        med = lambda v: float(np.median(v)) if v else None  # noqa: E731
        return {"method": self.method, "clips": len(x), "mean_rmse_m": float(x.mean()) if len(x) else None,
                "mean_ci_low_m": lo, "mean_ci_high_m": hi, "median_rmse_m": float(np.median(x)) if len(x) else None,
                "median_ci_low_m": mlo, "median_ci_high_m": mhi, "runaways": self.runaways, "failures": self.failures,
                "median_steps_per_second": med(self.speed), "median_reprojection_px": med(self.reprojection),
                "median_nis_mean": med(self.nis_mean), "median_nis_in_95": med(self.nis_in_95),
                "restarts": self.restarts, "scored_without_truth": len(self.reprojection)}

    def measure(self, e: dict) -> None:
        """What one clip's metrics say of the method without truth."""
        _add_finite(self.reprojection, e.get("reprojection_rmse_px"))
        nis = e.get("nis") or {}
        _add_finite(self.nis_mean, nis.get("normalized_mean"))
        _add_finite(self.nis_in_95, nis.get("in_95"))
        self.restarts += int(e.get("restarts") or 0)


def _add_finite(to: list[float], v: Any) -> None:
    if isinstance(v, (int, float)) and math.isfinite(v):
        to.append(float(v))


def method_rows(outcomes: list[ClipOutcome]) -> list[dict[str, Any]]:
    """Per method (in order of first appearance): 3-D RMSE across the clips that scored it, the
    clips where it ran away (over 10× that clip's median; see :func:`pipeline.evaluation.metrics.runaways`),
    the clips where it gave no score (no estimate, or the clip failed), its median speed."""
    rows: dict[str, MethodRow] = {}
    for o in outcomes:
        for m, e in (o.metrics or {}).get("methods", {}).items():
            if not e.get("target"):
                rows.setdefault(m, MethodRow(m))
    for o in outcomes:
        methods = (o.metrics or {}).get("methods", {})
        away = set(runaways(o.metrics)) if o.metrics else set()
        for m, row in rows.items():
            e = methods.get(m)
            if e is None:
                row.failures += 1
                continue
            v = e.get("rmse")
            if isinstance(v, (int, float)) and math.isfinite(v):
                row.rmse.append(float(v))
                row.by_clip[o.clip] = float(v)
            elif (o.metrics or {}).get("has_truth"):
                row.failures += 1
            if e.get("steps_per_second"):
                row.speed.append(float(e["steps_per_second"]))
            row.runaways += m in away
            row.measure(e)
    return ranked([r.values() | {"_by_clip": r.by_clip} for r in rows.values()])


def ranked(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The rows sorted by mean 3-D RMSE (methods with none last, in their order), each with its
    paired difference to the first (the best): over the clips both scored, the mean of its RMSE
    minus the best's and a Student-t 95 % interval for it. Clips share their difficulty, so
    intervals across clips overlap for every good method while the paired one separates them."""
    rows = sorted(rows, key=lambda r: r["mean_rmse_m"] if r["mean_rmse_m"] is not None else math.inf)
    best = rows[0]["_by_clip"] if rows else {}
    for r in rows:
        mine = r.pop("_by_clip")
        both = [c for c in mine if c in best]
        d = np.array([mine[c] - best[c] for c in both])
        lo, hi = mean_ci(d, clip=False)
        r |= {"paired_clips": len(both), "paired_diff_m": float(d.mean()) if len(d) else None,
              "paired_diff_ci_low_m": lo, "paired_diff_ci_high_m": hi}
    return rows


def interval(lo: float, hi: float, signed: bool = False) -> str:
    """An interval in m as ``lo–hi`` mm (``—`` when there is none); ``signed``: with signs (a difference)."""
    if not (math.isfinite(lo) and math.isfinite(hi)):
        return "—"
    f = "+.2f" if signed else ".2f"
    return f"{1000 * lo:{f}} to {1000 * hi:{f}}" if signed else f"{1000 * lo:{f}}–{1000 * hi:{f}}"


def leaderboard(rows: list[dict[str, Any]]) -> Table:
    """The per-method table (mm), best mean and median marked."""
    mm = number(".2f", 1000)
    get = lambda k: [r[k] for r in rows]  # noqa: E731
    cols = [Column("clips", get("clips"), number("d")),
            Column("mean 3-D RMSE (mm)", get("mean_rmse_m"), mm, "min"),
            Column("95 % CI of mean", [interval(r["mean_ci_low_m"], r["mean_ci_high_m"]) for r in rows]),
            Column("median (mm)", get("median_rmse_m"), mm, "min"),
            Column("95 % CI of median", [interval(r["median_ci_low_m"], r["median_ci_high_m"]) for r in rows]),
            Column("vs best, paired (mm)", get("paired_diff_m"), number("+.2f", 1000)),
            Column("95 % CI, paired", [interval(r["paired_diff_ci_low_m"], r["paired_diff_ci_high_m"], signed=True)
                                       for r in rows]),
            Column("runaways", get("runaways"), number("d"), "min"),
            Column("failures", get("failures"), number("d"), "min"),
            Column("steps/s (median)", get("median_steps_per_second"), number(",.0f"))]
    return Table("method", [r["method"] for r in rows], cols,
                 ["Best first, by mean 3-D RMSE. Intervals across clips: Student t for the mean (lower end clipped "
                  "at 0), binomial order statistics for the median (none below 6 clips). Paired: each method's RMSE "
                  "minus the best method's on the same clips, its mean and Student-t interval (an interval above 0: "
                  "worse than the best beyond the clips' spread). A runaway's error is over 10× its clip's median; "
                  "a failure scored nothing. steps/s is wall-clock and varies with load."])


def truthless_board(rows: list[dict[str, Any]]) -> Table:
    """The per-method table of what the detections alone can say (clips without truth score no
    3-D error): reprojection error, the filters' innovation consistency, restarts."""
    get = lambda k: [r[k] for r in rows]  # noqa: E731
    cols = [Column("clips", get("scored_without_truth"), number("d")),
            Column("reprojection RMSE (px, median)", get("median_reprojection_px"), number(".2f"), "min"),
            Column("NIS / dof (median; 1 is consistent)", get("median_nis_mean"), number(".2f"), 1.0, (0.5, 2.0)),
            Column("in the 95 % NIS band (median)", get("median_nis_in_95"), number(".0%"), "max", (0.8, 1.0)),
            Column("restarts", get("restarts"), number("d"), "min"),
            Column("failures", get("failures"), number("d"), "min")]
    return Table("method", [r["method"] for r in rows], cols,
                 ["Without truth: no 3-D error can be scored, and these say only how well the estimates agree with "
                  "the detections and how consistent the filters are with their own noise model (a method that "
                  "copies the detections, triangulation, reprojects best without being best in 3-D). NIS for "
                  "filters only."])


def clip_table(outcomes: list[ClipOutcome], methods: list[str], out_root: Path | None = None) -> Table:
    """One row per clip: status, attempts, warnings, and each method's 3-D RMSE (mm)."""
    def rmse(o, m):
        return ((o.metrics or {}).get("methods", {}).get(m) or {}).get("rmse")

    cols = [Column("status", [o.status for o in outcomes]), Column("attempts", [o.attempts for o in outcomes], str),
            Column("warnings", [len(clip_warnings(o)) for o in outcomes], str),
            *[Column(m, [rmse(o, m) for o in outcomes], number(".2f", 1000)) for m in methods],
            Column("error", [o.error or "" for o in outcomes])]
    # a link only to a report of this batch's outcome that is there (a failed clip's folder may hold an
    # older run's; a clip completed by an older stereotrack may have none)
    links = [f"{o.clip}/{REPORT_HTML}" if out_root is not None and o.status != "failed"
             and Outputs(out_root / o.clip).report_html.is_file() else None for o in outcomes]
    return Table("clip", [o.clip for o in outcomes], cols, links=links)


def write_summary(out_root: Path, outcomes: list[ClipOutcome]) -> list[dict[str, Any]]:
    """``summary.csv``, ``summary_methods.csv``, ``summary.md`` and ``summary.html``; returns
    the per-method rows (for the terminal)."""
    rows = []
    for o in outcomes:
        methods = o.metrics.get("methods", {}) if o.metrics else {}
        if not methods:
            rows.append((o.clip, o.status, "", "", "", "", "", o.attempts, o.error))
        for m, e in methods.items():
            rows.append((o.clip, o.status, m, e.get("rmse", ""), e.get("final", ""), e.get("reprojection_rmse_px", ""),
                         e.get("steps_per_second", ""), o.attempts, o.error))
    write_csv(out_root / "summary.csv", SUMMARY_COLUMNS, rows)
    per_method = method_rows(outcomes)
    write_csv(out_root / "summary_methods.csv", METHOD_COLUMNS, [[r[k] for k in METHOD_COLUMNS] for r in per_method])
    board = leaderboard(per_method)
    point = [r["method"] for r in per_method]
    n_fail = sum(o.status == "failed" for o in outcomes)
    head = f"{len(outcomes)} clips, {n_fail} failed."
    notes = [(o.clip, w) for o in outcomes for w in clip_warnings(o)]
    truthless = [o for o in outcomes if o.metrics and not o.metrics.get("has_truth")]
    blind = truthless_board(per_method) if truthless else None
    blind_head = (f"## Methods across clips, without truth ({len(truthless)} of {len(outcomes)} clips have none: "
                  "scored by the detections alone)")
    md = ["# stereotrack batch summary", "", head, "", "## Methods across clips", "", to_markdown(board), "",
          *([blind_head, "", to_markdown(blind), ""] if blind else []),
          "## Clips (3-D RMSE, mm)", "", to_markdown(clip_table(outcomes, point)), ""]
    if notes:
        md += ["## Warnings", "", *[f"- **{c}**: {w}" for c, w in notes], ""]
    write_text(out_root / "summary.md", "\n".join(md))
    body = ["<h1>stereotrack batch summary</h1>", f"<p>{head}</p>",
            "<p>" + " &nbsp; ".join(H.swatch(method_hex(m), m) for m in point) + "</p>",
            "<h2>Methods across clips</h2>", to_html(board),
            *([f"<h2>{inline(blind_head[3:])}</h2>", to_html(blind)] if blind else []),
            "<h2>Clips (3-D RMSE, mm; each links to its report)</h2>", to_html(clip_table(outcomes, point, out_root))]
    if notes:
        body += ["<h2>Warnings</h2><ul>", *[f"<li><b>{inline(c)}</b>: {inline(w)}</li>" for c, w in notes], "</ul>"]
    write_text(out_root / "summary.html", H.page("stereotrack batch summary", body))
    return per_method
