"""Identical markers through the whole pipeline: a rendered clip of same-coloured spheres (one
group, identities only in the truth) goes through `run`; the detector reports every blob of the
colour, the association makes tracks named ``<group>#<n>``, every method filters them, and
metrics.json scores them by identity against the truth; `estimate` alone reads the same from
detections.csv."""

from __future__ import annotations

import json

import numpy as np
import pytest

from detectors.stage import detect_clip
from pipeline.app.run import process_clip
from pipeline.core.clip import read_csv
from pipeline.core.settings import RunSettings
from pipeline.estimate import estimate_clip
from renderers.render import render_clip
from renderers.scenario import load_scenario, parse_scenario
from tests.helpers import read_trc

SCENARIO = {
    "name": "identical_small", "frames": 45, "fps": 30, "seed": 3,
    "rig": {"width": 640, "height": 480, "focal": 600, "baseline": 0.3},
    "render": {"shading": "flat", "noise_std": 2.0, "blur_sigma": 0.6},
    "objects": [{"name": f"o{i}", "color": [240, 150, 20], "radius": 0.03,
                 "motion": {"type": "constant_velocity", "start": [-0.3 + 0.2 * i, 0.08 * (i % 2) - 0.04, 2.4 + 0.1 * i],
                            "velocity": [0.25 * (-1) ** i, 0.0, 0.05]}} for i in range(4)],
}


@pytest.fixture(scope="module")
def identical_run(tmp_path_factory):
    clip = tmp_path_factory.mktemp("identical") / "clip"
    render_clip(parse_scenario(SCENARIO), clip, fmt="png", workers=1)
    res = process_clip(clip, settings=RunSettings(methods=("triangulation", "ekf"), images=False))
    return clip, res


@pytest.mark.slow
def test_identical_markers_run_end_to_end(identical_run):
    clip, res = identical_run
    info = json.loads((clip / "clip.json").read_text())
    group = {m["group"] for m in info["markers"]}
    assert len(group) == 1 and None not in group  # same colour, no group given: one group named after it
    g = group.pop()
    det = read_csv(res.out_dir / "detections.csv", ["frame", "camera", "marker"])
    per = {}
    for k, c, m in zip(det["frame"], det["camera"], det["marker"], strict=True):
        per[(k, c)] = per.get((k, c), 0) + (m == g)
    assert max(per.values()) == 4  # every blob of the colour, not one per colour
    truth = read_csv(clip / "truth.csv", ["marker", "group"])
    assert set(truth["group"]) == {g} and len(set(truth["marker"])) == 4  # each marker its identity, one group
    for method in ("triangulation", "ekf"):
        est = read_csv(res.out_dir / "estimates" / f"{method}.csv", ["marker", "x", "group"], numeric=["x"])
        names = set(est["marker"])
        assert names and all(n.startswith(f"{g}#") for n in names) and set(est["group"]) == {g}
        ident = res.estimate.metrics["methods"][method]["identity"][g]
        assert ident["idf1"] >= 0.8 and ident["mota"] >= 0.7, ident
        assert ident["id_switches"] <= 2, ident
        assert res.estimate.metrics["methods"][method]["rmse"] < 0.1  # errors against the marker each track follows
    assert not [c for c in res.estimate.metrics["checks"] if not c["ok"] and c["name"] == "stereo_pairs"]
    report = (res.out_dir / "report.md").read_text()
    section = report.split(f"## Identity: {g}", 1)[1]  # the report's identity table, one row per method
    assert "| IDF1 |" in section and "| triangulation |" in section and "| ekf |" in section


@pytest.mark.slow
def test_detections_number_the_blobs_and_flag_merged_ones(tmp_path):
    """detections.csv numbers a group's blobs per frame and camera (0, 1, …) and flags a blob as
    merged by its size and shape: against the truth (the built-in ``identical``, ten spheres, whose
    images merge often), a flagged blob holds two or more markers' images (their true pixels inside
    its equivalent radius) and at least half of such blobs are flagged."""
    clip = tmp_path / "clip"
    scenario = load_scenario("identical").model_copy(update={"frames": 60})
    render_clip(scenario, clip, fmt="png", workers=1)
    res = detect_clip(clip, out_dir=tmp_path / "out")
    det = read_csv(res.path, ["frame", "camera", "index", "merged", "area"])
    truth = read_csv(clip / "truth.csv", ["frame"])
    for k, c in {(k, c) for k, c in zip(det["frame"], det["camera"], strict=True)}:
        mine = (det["frame"] == k) & (det["camera"] == c)
        assert sorted(det["index"][mine]) == list(range(mine.sum()))
    many = np.zeros(len(det["frame"]), dtype=bool)
    for r, (k, c) in enumerate(zip(det["frame"], det["camera"], strict=True)):
        at = truth["frame"] == k
        uv = np.c_[truth[f"u_{c}_pinhole"][at], truth[f"v_{c}_pinhole"][at]]
        many[r] = (np.linalg.norm(uv - [det["u"][r], det["v"][r]], axis=1) < np.sqrt(det["area"][r] / np.pi)).sum() >= 2
    flagged = det["merged"] == 1
    assert many.sum() >= 5 and flagged.any()
    assert (many & flagged).sum() >= 0.9 * flagged.sum() and (many & flagged).sum() >= 0.5 * many.sum()


@pytest.mark.slow
def test_estimate_alone_reads_the_groups_from_detections_csv(identical_run, tmp_path):
    """`estimate` on its own, from detections.csv and the clip: the same tracks and identity scores."""
    clip, res = identical_run
    alone = estimate_clip(clip, RunSettings(methods=("ekf",)), out_dir=tmp_path, in_dir=res.out_dir)
    a, b = alone.metrics["methods"]["ekf"], res.estimate.metrics["methods"]["ekf"]
    (g, mine), (_, theirs) = next(iter(a["identity"].items())), next(iter(b["identity"].items()))
    assert a["identity"].keys() == b["identity"].keys() and mine.keys() == theirs.keys()
    for key, value in mine.items():  # detections.csv holds the pixels to its printed precision
        assert value == pytest.approx(theirs[key], rel=1e-6, abs=1e-9), (g, key)
    assert np.isclose(a["rmse"], b["rmse"])


@pytest.mark.slow
def test_export_writes_one_label_per_track(identical_run, tmp_path):
    """TRC export: one labelled marker per track of the group, never two tracks under one label."""
    from pipeline.present.export import export_clip

    clip, res = identical_run
    names = sorted(set(read_csv(res.out_dir / "estimates" / "ekf.csv", ["marker"])["marker"]))
    (path,) = export_clip(clip, "trc", ["ekf"], tmp_path)
    _, labels, _ = read_trc(path)  # read as OpenSim and as Pose2Sim read it, the two agreeing exactly
    assert sorted(labels) == names and len(labels) == len(set(labels))


@pytest.mark.slow
def test_recording_marks_births_and_ends(identical_run):
    """The recording's timeline carries each track's birth and end as events, per method."""
    from tests.pipeline.test_pipeline import read_recording

    _, res = identical_run
    cols, _, _ = read_recording(res.recording)
    texts = [t for c, v in cols.get("/events/ekf", cols.get("events/ekf", {})).items() if "Text" in c for t in v]
    flat = [x for t in texts for x in (t if isinstance(t, list) else [t])]
    tracks = set(read_csv(res.out_dir / "estimates" / "ekf.csv", ["marker"])["marker"])
    assert {f"{n} born" for n in tracks} <= set(flat) and {f"{n} ended" for n in tracks} <= set(flat), flat


@pytest.mark.slow
def test_report_figures_score_and_draw_the_group(identical_run):
    """The report of identical markers: each track's error per frame is against the marker it
    follows (read back from the stage files, its RMS is the metrics' RMSE), the error figure draws
    every method, and the trajectories draw every member's truth beside the tracks."""
    from pipeline.core.clip import Clip
    from pipeline.present.figures import FIGURES
    from pipeline.present.report_data import load_report_data

    clip, res = identical_run
    data = load_report_data(Clip.open(clip), res.out_dir, res.out_dir)
    for method in ("triangulation", "ekf"):
        e = np.concatenate(list(data.errors[method].values()))
        rms = float(np.sqrt(np.nanmean(e**2)))
        # the CSV keeps 10 significant digits of each position
        assert rms == pytest.approx(res.estimate.metrics["methods"][method]["rmse"], rel=1e-6)
    figs = dict(FIGURES)
    fig, _ = figs["error"](data)
    assert set(fig.axes[0].names()) >= {"triangulation", "ekf"}
    fig, _ = figs["trajectories"](data)
    truth_lines = [n for n in fig.axes[0].names() if n == "truth"]
    assert len(truth_lines) == len(data.groups[next(iter(data.groups))]) == 4


@pytest.mark.slow
def test_methods_in_worker_processes_write_what_one_process_writes(identical_run, tmp_path):
    """#42: `estimate` runs its methods in forked workers; the group's association is made once,
    before they fork, and every estimate and score is what one process writes."""
    from tests.pipeline.test_workers import assert_same_estimates

    clip, res = identical_run
    settings = RunSettings(methods=("triangulation", "ekf", "kf3d", "alphabeta"))
    one = estimate_clip(clip, settings, out_dir=tmp_path / "one", in_dir=res.out_dir, workers=1)
    two = estimate_clip(clip, settings, out_dir=tmp_path / "two", in_dir=res.out_dir, workers=2)
    assert_same_estimates(one, two)
    assert all("identity" in two.metrics["methods"][m] for m in settings.methods or ())
