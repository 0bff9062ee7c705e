"""What a person sees: report.html self-contained and complete, method colours distinct, figures
drawn only from the run's own methods, runaways clipped, the batch leaderboard."""

from __future__ import annotations

import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pytest

from pipeline.core.clip import Clip
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from pipeline.present.figures import FIGURES
from pipeline.present.report import write_report
from pipeline.present.report_data import load_report_data
from pipeline.present.style import PALETTE, TRUTH_RGB, delta_e, method_rgb
from tests.pipeline.test_pipeline import e2e_run  # noqa: F401  (the module's end-to-end run)

#: the smallest CIE76 ΔE between any two methods' colours, and between a method and the truth
MIN_DELTA_E = 30.0


class _Page(HTMLParser):
    """Every attribute value and the text of row headers."""

    def __init__(self) -> None:
        super().__init__()
        self.attrs: list[tuple[str, str]] = []
        self.rows: list[str] = []
        self._in_row = False

    def handle_starttag(self, tag, attrs):
        self.attrs += [(k, v or "") for k, v in attrs]
        if tag in ("th", "td"):
            self._in_row = tag == "th" and ("scope", "row") in attrs

    def handle_data(self, data):
        if self._in_row and data.strip():
            self.rows.append(data.strip())
            self._in_row = False


def parse(path: Path) -> _Page:
    page = _Page()
    page.feed(path.read_text())
    return page


def test_method_colours_are_distinct():
    """No two registered methods' colours closer than MIN_DELTA_E (CIE76 in CIELAB), nor any to
    the truth's black; the measure itself: black to white is 100."""
    from pipeline.estimators import registry

    names = list(registry())
    assert delta_e((0, 0, 0), (255, 255, 255)) == pytest.approx(100, abs=0.1)
    worst = min(delta_e(method_rgb(a), method_rgb(b)) for i, a in enumerate(names) for b in names[i + 1:])
    assert worst >= MIN_DELTA_E, worst
    assert min(delta_e(method_rgb(m), TRUTH_RGB) for m in names) >= MIN_DELTA_E
    assert min(delta_e(a, b) for i, a in enumerate(PALETTE) for b in PALETTE[i + 1:]) >= MIN_DELTA_E


@pytest.mark.slow
def test_report_html_is_self_contained_and_lists_every_method(e2e_run):  # noqa: F811
    html = e2e_run.out_dir / "report.html"
    page = parse(html)
    figures = len(list((e2e_run.out_dir / "figures").glob("*.svg")))
    assert figures >= 3 and html.read_text().count("<svg ") == figures  # every figure inline
    assert not [v for k, v in page.attrs if k in ("href", "src") and "://" in v]
    methods = list(e2e_run.estimate.metrics["methods"])
    assert set(methods) <= set(page.rows)
    text = html.read_text()
    assert all(f"</span>{m}" in text for m in methods)  # the colour legend
    assert "stereotrack view" in text and "Checks" in text


@pytest.mark.slow
def test_the_report_command_draws_its_figures_without_matplotlib(e2e_run, tmp_path):  # noqa: F811
    """#42: matplotlib's import alone took longer than the detect stage; the figures are SVG."""
    from tests.pipeline.test_startup import loaded

    clip = tmp_path / "clip"
    shutil.copytree(e2e_run.clip, clip)
    shutil.rmtree(clip / "out" / "figures")
    mods = loaded(f"import sys; sys.argv = ['stereotrack', 'report', {str(clip)!r}]\n"
                  "from pipeline.app.cli import main\nmain()")
    assert "pipeline" in mods and (clip / "out" / "figures" / "error.svg").is_file()
    assert not mods & {"matplotlib", "PIL", "scipy", "filterpy"}, sorted(mods & {"matplotlib", "PIL", "scipy", "filterpy"})


@pytest.mark.slow
def test_figures_draw_the_runs_methods_only(e2e_run, tmp_path):  # noqa: F811
    """A stale estimate CSV from an earlier run (a method not in metrics.json) is not drawn; every
    figure's legend lists every method it plots and the truth."""
    out = tmp_path / "out"
    shutil.copytree(e2e_run.out_dir, out)
    shutil.copy(out / "estimates" / "ekf.csv", out / "estimates" / "stale_method.csv")
    write_report(Clip.open(e2e_run.clip), out)
    assert "stale_method" not in (out / "report.html").read_text() + (out / "report.md").read_text()
    data = load_report_data(Clip.open(e2e_run.clip), out, out)
    assert "stale_method" not in data.point
    figs = dict(FIGURES)
    methods = set(e2e_run.estimate.metrics["methods"])
    assert figs["trajectories"](data)[0].legend_labels() == methods | {"truth"}
    assert figs["error"](data)[0].legend_labels() == methods


@pytest.mark.slow
def test_runaways_are_clipped_and_named(e2e_run, tmp_path):  # noqa: F811
    """A method whose error is far above the others' sets no axis: the error figure's y range is
    that of the tracking methods, and the caption and tables name the runaway."""
    data = load_report_data(Clip.open(e2e_run.clip), e2e_run.out_dir, e2e_run.out_dir)
    T = data.truth["red"]
    data.point["runaway"] = {"red": T + np.array([0.0, 0.0, 5.0])}  # 5 m off every frame
    data.errors["runaway"] = {"red": np.full(len(T), 5.0)}
    data.metrics["methods"]["runaway"] = {"rmse": 5.0}
    fig, caption = dict(FIGURES)["error"](data)
    assert "runaway (RMSE 5e+03 mm)" in caption and fig.axes[0].limits()[1][1] < 1000  # mm


@pytest.mark.slow
def test_batch_summary_html(tmp_path):
    """Three clips: summary.html has one row per method with its confidence intervals, and every
    link resolves to a clip's report."""
    from pipeline.app.batch import run_batch
    from tests.conftest import REPO

    inp = tmp_path / "in"
    for name in ("a", "b", "c"):
        shutil.copytree(REPO / "data" / "clips" / "sample_small", inp / name)
    out = tmp_path / "out"
    run_batch(inp, out, RunSettings(methods=["triangulation", "ekf"], images=False, figures=False), workers=1)
    page = parse(out / "summary.html")
    board = read_csv(out / "summary_methods.csv")
    assert page.rows[:2] == list(board["method"]) and {"a", "b", "c"} <= set(page.rows)
    assert list(board["mean_rmse_m"]) == sorted(board["mean_rmse_m"])  # best first
    links = [v for k, v in page.attrs if k == "href"]
    assert len(links) == 3 and all((out / v).is_file() for v in links)
    text = (out / "summary.html").read_text()
    assert "95 % CI of mean" in text and text.count("–") >= 2  # an interval per method
    board, long = read_csv(out / "summary_methods.csv"), read_csv(out / "summary.csv")
    for m, clips, mean in zip(board["method"], board["clips"], board["mean_rmse_m"], strict=True):
        assert clips == 3 and mean == pytest.approx(np.mean(long["rmse_m"][long["method"] == m]), rel=1e-6)


@pytest.mark.slow
def test_report_from_memory_equals_report_from_files(e2e_run):  # noqa: F811
    """`run` draws the report from its results in memory; `stereotrack report` reads the stage
    files back: the same data either way (to the CSVs' 10 significant digits)."""
    from pipeline.present.report_data import report_data

    clip = Clip.open(e2e_run.clip)
    mem = report_data(clip, e2e_run.estimate, e2e_run.detect.marker_colours, e2e_run.out_dir)
    disk = load_report_data(clip, e2e_run.out_dir, e2e_run.out_dir)
    assert mem.point.keys() == disk.point.keys() and mem.filters.keys() == disk.filters.keys()
    for m in mem.point:
        for mk in mem.point[m]:
            np.testing.assert_allclose(mem.point[m][mk], disk.point[m][mk][: len(mem.point[m][mk])], rtol=1e-8)
    for m in mem.filters:
        for a, b in zip(mem.filters[m], disk.filters[m], strict=True):
            np.testing.assert_allclose(a, b, rtol=1e-6, atol=1e-9)
    for mk in mem.obs:
        np.testing.assert_allclose(mem.obs[mk], disk.obs[mk][: len(mem.obs[mk])], rtol=1e-8)
    assert mem.marker_colours == disk.marker_colours and mem.metrics == disk.metrics


@pytest.mark.slow
def test_run_reads_each_input_once(tmp_path, monkeypatch):
    """One `run`: the calibration is loaded once, the markers resolved once, and no stage reads
    back a file another stage wrote (the estimate and report stages take their inputs in memory)."""
    import detectors.markers
    import detectors.stage
    import pipeline.core.clip
    import pipeline.core.io
    import pipeline.present.report_data
    from pipeline.app.run import process_clip
    from tests.conftest import REPO

    clip = tmp_path / "clip"
    shutil.copytree(REPO / "data" / "clips" / "sample_small", clip)
    calls: dict[str, list] = {"calibration": [], "markers": [], "read_csv": [], "read_json": []}

    def spy(module, name, key):
        real = getattr(module, name)

        def wrapped(*a, **kw):
            calls[key].append(a[0] if a else None)
            return real(*a, **kw)
        monkeypatch.setattr(module, name, wrapped)

    spy(pipeline.core.clip, "load_calibration", "calibration")
    spy(detectors.stage, "resolve_marker_specs", "markers")
    spy(pipeline.core.clip, "read_csv", "read_csv")
    spy(pipeline.core.io, "read_csv", "read_csv")
    spy(pipeline.core.clip, "read_json_mapping", "read_json")
    spy(pipeline.present.report_data, "read_csv", "read_csv")
    spy(pipeline.present.report_data, "read_json_mapping", "read_json")
    res = process_clip(clip, settings=RunSettings(methods=["triangulation", "ekf"], images=False))
    assert len(calls["calibration"]) == 1 and len(calls["markers"]) == 1, calls
    outputs = [p for p in calls["read_csv"] + calls["read_json"] if p is not None and res.out_dir in Path(p).parents]
    assert not outputs, outputs
    assert (res.out_dir / "report.html").is_file()


def test_long_series_are_thinned_to_what_a_figure_shows():
    """Past MAX_LINE_POINTS a per-frame series keeps each bucket's extremes in frame order (a
    one-frame spike and a gap survive) and a path every k-th point and its end; shorter ones are
    drawn whole."""
    from pipeline.present.figures import MAX_LINE_POINTS, _envelope, _thin

    rng = np.random.default_rng(0)
    y = rng.normal(10.0, 1.0, 7001)
    y[4321], y[100:200] = 500.0, np.nan
    x, v = _envelope(y)
    assert len(v) <= MAX_LINE_POINTS and np.all(np.diff(x) > 0)
    np.testing.assert_array_equal(v, y[x])
    assert 4321 in x and np.nanmin(v) == np.nanmin(y) and np.isnan(v[(x >= 100) & (x < 200)]).all()
    a, b = _thin(np.arange(7001.0), y)
    np.testing.assert_array_equal(b, y[a.astype(int)])
    assert len(a) <= MAX_LINE_POINTS + 1 and a[-1] == 7000 and np.all(np.diff(a) > 0)
    short = np.arange(50.0)
    assert _envelope(short)[1] is short and _thin(short)[0] is short


def test_the_checks_never_say_all_passed_above_a_failed_line():
    """#41 item 8: estimates behind a camera were listed as a failed line under "All input checks
    passed"."""
    from pipeline.present.report import check_lines, checks_section

    metrics = {"checks": [{"name": "sync", "ok": True, "message": "fine"}],
               "methods": {"spsa": {"behind_camera": 3}, "ekf": {"behind_camera": 0}}}
    failed, lines = check_lines(metrics)
    assert failed == 1 and (False, "estimates behind a camera (counted, not drawn): spsa 3") in lines
    text = "\n".join(checks_section(metrics))
    assert "All input checks passed" not in text and "1 check(s) failed" in text


def test_a_report_without_truth_has_no_truth_in_its_colour_key(tmp_path):
    """#41 item 8: a run without truth still listed "truth (dashed)" in its colour key."""
    from pipeline.present.report import html_report
    from pipeline.present.report_data import ReportData

    for has_truth in (False, True):
        data = ReportData("clip", tmp_path, {"has_truth": has_truth, "methods": {"ekf": {}}, "frames": 3, "dt": 0.1})
        assert ("truth (dashed)" in html_report(data, [], "stereotrack view x")) == has_truth


def test_no_filter_is_marked_best_at_consistency_when_all_fail():
    """#41 item 8: the consistency table marked the "best" cell even when every filter failed its band."""
    from pipeline.present.report import consistency_table

    def entry(nees: float, band: float) -> dict:
        return {"nees_position": {"normalized_mean": nees, "in_95": band}, "nis": {"normalized_mean": nees, "in_95": band}}

    failing = consistency_table({"methods": {"ekf": entry(11.6, 0.78), "ukf": entry(9.0, 0.70)}})
    assert all(c.best_row() is None for c in failing.columns)
    mixed = consistency_table({"methods": {"ekf": entry(1.05, 0.90), "ukf": entry(9.0, 0.70), "kf3d": entry(0.7, 0.95)}})
    assert [c.best_row() for c in mixed.columns] == [0, 2, 0, 2]


def test_leaderboard_is_best_first_with_paired_differences():
    """Clips differ in difficulty far more than methods do: every method's interval across clips
    overlaps the best's, but the paired differences (same clips) separate a method 0.5 mm worse
    on every clip from one as good as the best, and the board is sorted by mean error."""
    from pipeline.present.summary import ClipOutcome, leaderboard, method_rows

    rng = np.random.default_rng(3)
    hard = [0.002, 0.010, 0.030, 0.006, 0.050, 0.015]  # each clip's difficulty, m
    err = {"worse": [h + 0.0005 + rng.normal(0, 1e-5) for h in hard], "best": list(hard),
           "twin": [h + rng.normal(0, 1e-5) for h in hard]}
    outcomes = [ClipOutcome(f"c{i}", "ok", {"has_truth": True, "methods": {m: {"rmse": e[i]} for m, e in err.items()}})
                for i in range(len(hard))]
    rows = {r["method"]: r for r in method_rows(outcomes)}
    assert list(rows) == ["best", "twin", "worse"]  # best first
    worse, twin = rows["worse"], rows["twin"]
    assert worse["mean_ci_low_m"] < rows["best"]["mean_rmse_m"] < worse["mean_ci_high_m"]  # unpaired: overlap
    assert 0 < worse["paired_diff_ci_low_m"] < 0.0005 < worse["paired_diff_ci_high_m"]  # paired: above 0, holds 0.5 mm
    assert twin["paired_diff_ci_low_m"] < 0 < twin["paired_diff_ci_high_m"] and worse["paired_clips"] == 6
    assert rows["best"]["paired_diff_m"] == 0.0
    text = "\n".join(str(c) for c in leaderboard(list(rows.values())).columns)
    assert "vs best, paired (mm)" in text

