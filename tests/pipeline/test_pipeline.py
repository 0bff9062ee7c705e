"""End to end: render → detect → estimate → metrics → report → recording, the CLI, and batch."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from xml.etree import ElementTree

import numpy as np
import pytest
from typer.testing import CliRunner

from pipeline.app.batch import find_clips, run_batch
from pipeline.app.cli import app
from pipeline.app.run import process_clip
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from pipeline.present.recording import DETECTION_RING
from pipeline.present.style import TRUTH_RGB_VIEWER
from renderers.render import render_clip
from renderers.scenario import parse_scenario
from tests.conftest import REPO

METHODS = ["triangulation", "ekf", "kf3d", "spsa", "alphabeta"]


def noisy_receding(seed: int = 1) -> dict:
    """320×240, 40 frames, a small marker and strong sensor noise: triangulation is noisy here."""
    return {"name": "e2e", "frames": 40, "fps": 30, "seed": seed,
            "rig": {"width": 320, "height": 240, "focal": 300, "baseline": 0.25, "toe_in_deg": 2},
            "render": {"noise_std": 8, "blur_sigma": 1.0},
            "objects": [{"name": "red", "color": [230, 30, 30], "radius": 0.03,
                         "motion": {"type": "constant_velocity", "start": [-0.2, 0.05, 2.0], "velocity": [0.2, 0.0, 1.2]}}]}


@pytest.fixture(scope="module")
def e2e_run(tmp_path_factory):
    clip = tmp_path_factory.mktemp("e2e") / "clip"
    render_clip(parse_scenario(noisy_receding()), clip, fmt="mp4", workers=1)
    return process_clip(clip, settings=RunSettings(methods=METHODS))


@pytest.mark.slow
def test_end_to_end_accuracy(e2e_run):
    m = e2e_run.estimate.metrics["methods"]
    assert m["ekf"]["rmse"] < m["triangulation"]["rmse"]
    assert m["kf3d"]["rmse"] < m["triangulation"]["rmse"]
    assert m["spsa"]["rmse"] < 0.5 and np.isfinite(m["spsa"]["final"])  # bounded
    assert 0.02 < e2e_run.estimate.metrics["pixel_sigma_estimate"] < 1.0
    out = e2e_run.out_dir
    on_disk = json.loads((out / "metrics.json").read_text())
    assert on_disk["methods"]["ekf"]["rmse"] == pytest.approx(m["ekf"]["rmse"])
    for meth in METHODS:
        cols = read_csv(out / "estimates" / f"{meth}.csv", ["frame", "t", "marker", "x", "y", "z", "vx", "vy", "vz"])
        assert len(cols["frame"]) == 40


def test_every_file_written_is_documented(e2e_run):
    """The Files page is generated from ``Outputs.files`` and the schemas: every file of a run's
    output folder is listed there, and every table's header is its schema's."""
    from pipeline.core.clip import DETECTIONS, ESTIMATES, TIMESTAMPS_SCHEMA, TRUTH
    from pipeline.core.outputs import Outputs

    out = e2e_run.out_dir
    assert {p.name for p in out.iterdir()} <= {f.name for f in Outputs.files()}
    header = lambda p: p.read_text().splitlines()[0].split(",")  # noqa: E731
    assert header(out / "detections.csv") == DETECTIONS.names
    assert {p.stem for p in (out / "estimates").iterdir()} == set(METHODS)
    assert all(header(p) == ESTIMATES.names for p in (out / "estimates").iterdir())
    assert header(out.parent / "truth.csv") == TRUTH.names
    assert header(out.parent / "timestamps.csv") == TIMESTAMPS_SCHEMA.names


@pytest.mark.slow
def test_report_written(e2e_run):
    text = e2e_run.report.read_text()
    assert "| ekf |" in text and "figures/trajectories.svg" in text and "figures/error.svg" in text
    for fig in ("trajectories.svg", "error.svg", "image_tracks.svg"):
        svg = e2e_run.out_dir / "figures" / fig
        assert svg.is_file() and ElementTree.parse(svg).getroot().tag == "{http://www.w3.org/2000/svg}svg"


def read_recording(path) -> tuple[dict[str, dict[str, list]], set[str], object]:
    """``entity → column → values`` (rows in frame order, static chunks under column names too),
    the static entities, and the reader."""
    from rerun.chunk import RrdReader

    reader = RrdReader(path)
    cols: dict[str, dict[str, list]] = {}
    static: set[str] = set()
    for chunk in reader.stream():
        rb = chunk.to_record_batch()
        if chunk.is_static:
            static.add(chunk.entity_path)
        for name in rb.schema.names:
            if name in ("log_time", "time", "rerun.controls.RowId", "RecordingInfo:start_time"):
                continue
            cols.setdefault(chunk.entity_path, {}).setdefault(name, []).extend(rb.column(name).to_pylist())
    return cols, static, reader


def _untimed(d):
    """A metrics mapping without its timings (steps per second differ from run to run)."""
    if isinstance(d, dict):
        return {k: _untimed(v) for k, v in d.items() if k not in ("seconds_per_step", "steps_per_second")}
    return [_untimed(v) for v in d] if isinstance(d, list) else d


@pytest.mark.slow
def test_streamed_run_writes_what_a_kept_run_writes(e2e_run, tmp_path, monkeypatch):
    """`stereotrack run` and batches hand each method's tracks to the report and the recording as
    the method finishes and then drop them (``keep_tracks=False``: memory flat in clip length).
    Metrics, estimates, figures and recording equal those of a run that keeps every track, and
    no track outlives the run."""
    import gc
    import weakref

    import pipeline.present.report

    seen: list[weakref.ref] = []
    add = pipeline.present.report.ReportData.add_method

    def spy(self, est, m, per, scores):
        seen.extend(weakref.ref(t) for t in per.values())
        return add(self, est, m, per, scores)

    monkeypatch.setattr(pipeline.present.report.ReportData, "add_method", spy)
    res = process_clip(e2e_run.clip, settings=RunSettings(methods=METHODS), out_dir=tmp_path / "out", keep_tracks=False)
    gc.collect()
    assert len(seen) == len(METHODS) and not [r for r in seen if r() is not None]
    assert not res.estimate.tracks and set(e2e_run.estimate.tracks) == set(METHODS)
    assert _untimed(res.estimate.metrics) == _untimed(e2e_run.estimate.metrics)
    kept, streamed = e2e_run.out_dir, res.out_dir
    for meth in METHODS:
        assert (streamed / "estimates" / f"{meth}.csv").read_bytes() == (kept / "estimates" / f"{meth}.csv").read_bytes()
    figures = sorted(p.name for p in (kept / "figures").iterdir())
    assert figures == sorted(p.name for p in (streamed / "figures").iterdir()) and "trajectories.svg" in figures
    for name in figures:
        assert (streamed / "figures" / name).read_bytes() == (kept / "figures" / name).read_bytes(), name
    a, b = read_recording(e2e_run.recording)[0], read_recording(res.recording)[0]
    assert a == b and all(f"/world/estimates/{meth}/points" in b for meth in METHODS)


@pytest.mark.slow
def test_recording_read_back(e2e_run):
    """Images (JPEG), cameras, every method's points, series and the blueprint, with values."""
    import cv2

    cols, static, reader = read_recording(e2e_run.recording)
    assert reader.recordings() and reader.blueprints()  # the blueprint is saved as the default
    rig = e2e_run.estimate.rig
    assert {"/world/left", "/world/right"} <= static  # calibration logged once, static
    for name, cam in zip(("left", "right"), rig.cameras, strict=True):
        K = np.array(cols[f"/world/{name}"]["Pinhole:image_from_camera"][0]).reshape(3, 3).T  # column-major
        np.testing.assert_allclose(K, cam.K, rtol=1e-6)
        np.testing.assert_allclose(np.ravel(cols[f"/world/{name}"]["Transform3D:translation"][0]), cam.center, atol=1e-6)
        img = cols[f"/world/{name}/image"]
        assert img["frame"] == list(range(40)) and {m[0] for m in img["EncodedImage:media_type"]} == {"image/jpeg"}
        first = cv2.imdecode(np.frombuffer(bytes(img["EncodedImage:blob"][0][0]), np.uint8), cv2.IMREAD_COLOR)
        assert first.shape == (240, 320, 3)
    # detections: rings around the pixel coordinates of detections.csv, labelled with the marker
    det = e2e_run.estimate.observations["red"]
    d = cols["/world/left/detections"]
    for k, ring, lab in zip(d["frame"], d["LineStrips2D:strips"], d["LineStrips2D:labels"], strict=True):
        np.testing.assert_allclose(np.mean(ring[0][:-1], axis=0), det[k, :2], atol=1e-3)  # closed: last = first
        radius = DETECTION_RING * rig.sizes[0][0]  # a fraction of the image's width: the same size in any pane
        np.testing.assert_allclose(np.linalg.norm(np.array(ring[0]) - det[k, :2], axis=1), radius, atol=1e-3)
        assert lab == ["red"]
    truth = e2e_run.estimate.truth.positions["red"]
    np.testing.assert_allclose(np.array(cols["/world/truth/points"]["Points3D:positions"])[:, 0], truth, atol=1e-5)
    colours = set()
    for meth in METHODS:
        tr = e2e_run.estimate.tracks[meth]["red"]
        p = cols[f"/world/estimates/{meth}/points"]
        started = np.flatnonzero(np.all(np.isfinite(tr.position), axis=1))
        held = [(k, v) for k, v in zip(p["frame"], p["Points3D:positions"], strict=True) if v]
        assert [k for k, _ in held] == started.tolist()
        np.testing.assert_allclose(np.array([v[0] for _, v in held]), tr.position[started], atol=1e-5)
        # where the track has no estimate after having one, an empty batch: the view shows no stale point
        gone = [k for k in range(1, len(tr.position)) if k - 1 in started and k not in started]
        assert [k for k, v in zip(p["frame"], p["Points3D:positions"], strict=True) if not v] == gone
        colours.add(p["Points3D:colors"][0][0])
        e = cols[f"/metrics/error/red/{meth}"]
        want = np.linalg.norm(tr.position - truth, axis=1)
        np.testing.assert_allclose(np.array(e["Scalars:scalars"])[:, 0], 1000 * want[e["frame"]], rtol=1e-9)  # mm
    assert len(colours) == len(METHODS)  # one colour per method


def test_a_run_without_truth_names_its_markers_in_3d(tmp_path):
    """Without truth (a real rig's clip) the truth's labelled points are missing: the best method's
    points carry the markers' names instead (the other methods' on hover)."""
    from tests.helpers import real_copy

    clip = real_copy(tmp_path / "rig")
    result = CliRunner().invoke(app, ["run", str(clip), "--markers", "red=#e61e1e,blue=#283ce6",
                                      "--methods", "triangulation,kf3d,ukf"])
    assert result.exit_code == 0, result.output
    cols, _, _ = read_recording(clip / "out" / "run.rrd")
    labelled = {m for m in ("triangulation", "kf3d", "ukf")
                if cols[f"/world/estimates/{m}/points"].get("Points3D:show_labels", [[False]])[-1] == [True]}
    assert len(labelled) == 1, labelled


def test_run_cli_on_sample_clip(tmp_path):
    clip = tmp_path / "sample"
    shutil.copytree(REPO / "data" / "clips" / "four_point_small", clip)
    result = CliRunner().invoke(app, ["run", str(clip), "--methods", "ekf,kalman_bucy,pnp_kf,four_point"])
    assert result.exit_code == 0, result.output
    assert "kalman_bucy" in result.output and (clip / "out" / "run.rrd").is_file()
    metrics = json.loads((clip / "out" / "metrics.json").read_text())["methods"]
    assert metrics["kalman_bucy"]["alpha_rmse_rad"] < 0.05
    # a run with the four-point target shows its α and z, each method named, truth in the viewer's grey;
    # the true plate's outline and each target method's centre in 3-D
    cols, _, reader = read_recording(clip / "out" / "run.rrd")
    origins = [o for c in blueprint_columns(reader).values() for v in c.get("ViewBlueprint:space_origin", []) for o in v]
    assert "/metrics/target/alpha" in origins and "/metrics/target/distance" in origins
    assert cols["/metrics/target/alpha/kalman_bucy"]["SeriesLines:names"][0] == ["kalman_bucy"]
    assert cols["/metrics/target/alpha/truth"]["SeriesLines:colors"][0] == [packed(TRUTH_RGB_VIEWER)]
    assert len(cols["/world/truth/plate"]["LineStrips3D:strips"][0][0]) == 5  # a closed outline of 4 corners
    est = read_csv(clip / "out" / "estimates" / "kalman_bucy.csv", ["frame", "alpha", "distance"])
    for key, name in (("alpha", "alpha"), ("distance", "distance")):  # mrad and mm, as the report's tables
        series = cols[f"/metrics/target/{name}/kalman_bucy"]
        np.testing.assert_allclose(np.ravel(series["Scalars:scalars"]), 1000 * est[key][series["frame"]], rtol=1e-6)
    centre = cols["/world/estimates/kalman_bucy/points"]["Points3D:positions"]
    truth = read_csv(clip / "truth.csv")
    corners = np.array([truth["x"], truth["y"], truth["z"]]).T[truth["frame"] == 10]
    np.testing.assert_allclose(centre[10][0], corners.mean(axis=0), atol=0.03)


@pytest.mark.slow
def test_cli_errors_are_one_line(tmp_path):
    env = {**os.environ, "COLUMNS": "200"}
    for args in (["detect", str(tmp_path / "nope")], ["estimate", str(tmp_path)], ["run", "no_such_scenario"]):
        proc = subprocess.run([sys.executable, "-m", "pipeline.app.cli", *args], capture_output=True, text=True, env=env,
                              timeout=120)
        assert proc.returncode == 2, proc.stderr
        assert "Traceback" not in proc.stderr and "error:" in proc.stderr


def _batch_input(root: Path) -> Path:
    inp = root / "in"
    for i, name in enumerate(("a", "b")):
        shutil.copytree(REPO / "data" / "clips" / "sample_small", inp / name)
        if i:  # a second, different clip
            shutil.copytree(REPO / "data" / "clips" / "four_point_small", inp / name, dirs_exist_ok=True)
    bad = inp / "c_corrupt"
    shutil.copytree(REPO / "data" / "clips" / "sample_small", bad)
    (bad / "right.mp4").write_bytes(b"\x00garbage" * 100)
    return inp


def _summary(out: Path) -> list[tuple[str, str, str]]:
    cols = read_csv(out / "summary.csv")
    status = ["ok" if s == "skipped" else s for s in cols["status"]]  # skipped = complete from before
    return sorted(zip(cols["clip"], status, cols["method"], strict=True))


@pytest.mark.slow
def test_batch_local_then_rerun_then_dask(tmp_path):
    inp = _batch_input(tmp_path)
    assert [p.name for p in find_clips(inp)] == ["a", "b", "c_corrupt"]
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["batch", str(inp), "-o", str(out), "--workers", "2", "--methods", "triangulation,ekf"])
    assert res.exit_code == 1  # one clip failed
    outcomes = {o[0]: o[1] for o in _summary(out)}
    assert outcomes == {"a": "ok", "b": "ok", "c_corrupt": "failed"}
    cols = read_csv(out / "summary.csv")
    err = next(e for c, e in zip(cols["clip"], cols["error"], strict=True) if c == "c_corrupt")
    assert "right.mp4" in err
    assert (out / "a" / "report.md").is_file() and (out / "b" / "metrics.json").is_file()
    assert not (out / "c_corrupt").exists() and not list(out.glob(".*partial*"))
    assert "summary" in (out / "summary.md").read_text()
    # a second run redoes nothing that is complete
    mtime = (out / "a" / "metrics.json").stat().st_mtime_ns
    again = run_batch(inp, out, RunSettings(methods=["triangulation", "ekf"], figures=False), workers=1)
    assert {o.clip: o.status for o in again} == {"a": "skipped", "b": "skipped", "c_corrupt": "failed"}
    assert (out / "a" / "metrics.json").stat().st_mtime_ns == mtime
    # the same batch on a Dask LocalCluster gives the same summary
    out2 = tmp_path / "out_dask"
    dask = run_batch(inp, out2, RunSettings(methods=["triangulation", "ekf"], figures=False), workers=2, scheduler="local")
    assert {o.clip: o.status for o in dask} == {"a": "ok", "b": "ok", "c_corrupt": "failed"}
    assert _summary(out2) == _summary(out)
    ours, theirs = read_csv(out / "summary.csv"), read_csv(out2 / "summary.csv")
    np.testing.assert_allclose(np.sort(ours["rmse_m"][np.isfinite(ours["rmse_m"])]),
                               np.sort(theirs["rmse_m"][np.isfinite(theirs["rmse_m"])]), rtol=1e-9)


@pytest.mark.slow
def test_view_works_on_any_folder_with_a_recording(e2e_run, tmp_path, monkeypatch):
    """A batch's OUT/<clip> holds run.rrd directly: `view` finds it and, with no display, prints the
    viewer command."""
    batch_clip = tmp_path / "OUT" / "clip"
    batch_clip.mkdir(parents=True)
    shutil.copy(e2e_run.recording, batch_clip / "run.rrd")
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    for target, rrd in ((batch_clip, batch_clip / "run.rrd"), (e2e_run.clip, e2e_run.recording)):
        res = CliRunner().invoke(app, ["view", str(target)])
        assert res.exit_code == 0 and f"rerun {rrd}" in res.output.replace("\n", ""), res.output
    res = CliRunner().invoke(app, ["view", str(tmp_path / "OUT")])  # a batch output folder: every clip's
    assert res.exit_code == 0 and f"rerun {batch_clip / 'run.rrd'}" in res.output.replace("\n", "")
    (tmp_path / "empty").mkdir()
    res = CliRunner().invoke(app, ["view", str(tmp_path / "empty")])
    assert res.exit_code != 0 and "no recording" in str(res.exception)


@pytest.mark.slow
def test_view_web_runs_the_viewer_beside_python_and_passes_its_exit_code(e2e_run, tmp_path, monkeypatch):
    """`view --web` serves rerun's web viewer on 127.0.0.1, prints the URL, and the viewer's exit
    code is the command's (a fake viewer that exits 3 stands in for rerun)."""
    import pipeline.app.cli_batch as cli_module

    fake = tmp_path / "rerun"
    fake.write_text(f"#!/bin/sh\necho \"$@\" > {tmp_path / 'args'}\nexit 3\n")
    fake.chmod(0o755)
    monkeypatch.setattr(cli_module, "_viewer", lambda: str(fake))
    res = CliRunner().invoke(app, ["view", str(e2e_run.clip), "--web", "--port", "9190"])
    assert res.exit_code == 3, res.output
    assert "http://127.0.0.1:9190/?url=rerun%2Bhttp://127.0.0.1:9191/proxy" in res.output.replace("\n", "")
    args = (tmp_path / "args").read_text().split()
    assert args[:7] == ["--serve-web", "--bind", "127.0.0.1", "--web-viewer-port", "9190", "--port", "9191"]
    assert args[-1] == str(e2e_run.recording)


def test_version_and_plain_flags():
    res = CliRunner().invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.startswith("stereotrack ")
    helptext = CliRunner().invoke(app, ["batch", "--help"]).output
    assert "--no-images" in helptext and "--force" in helptext and "<bool>" not in helptext


def test_every_method_has_its_own_colour():
    from pipeline.estimators import registry
    from pipeline.present.style import method_hex, method_rgb

    names = list(registry())
    assert len({method_rgb(m) for m in names}) == len(names)
    assert method_hex("ekf") == "#{:02x}{:02x}{:02x}".format(*method_rgb("ekf"))


def test_output_option_is_output_only(tmp_path):
    """`estimate -o X` reads CLIP/out/detections.csv and writes only under X."""
    clip = tmp_path / "sample"
    shutil.copytree(REPO / "data" / "clips" / "sample_small", clip)
    assert CliRunner().invoke(app, ["detect", str(clip)]).exit_code == 0
    before = sorted(p.name for p in (clip / "out").iterdir())
    res = CliRunner().invoke(app, ["estimate", str(clip), "-o", str(tmp_path / "X"), "--methods", "ekf"])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "X" / "metrics.json").is_file() and (tmp_path / "X" / "estimates" / "ekf.csv").is_file()
    assert sorted(p.name for p in (clip / "out").iterdir()) == before


def blueprint_columns(reader) -> dict[str, dict[str, list]]:
    """The saved blueprint's ``entity → column → values``."""
    cols: dict[str, dict[str, list]] = {}
    for chunk in reader.stream(store=reader.blueprints()[0]):
        rb = chunk.to_record_batch()
        for name in rb.schema.names:
            if name not in ("log_time", "rerun.controls.RowId"):
                cols.setdefault(chunk.entity_path, {}).setdefault(name, []).extend(rb.column(name).to_pylist())
    return cols


def packed(rgb) -> int:
    r, g, b = rgb
    return (r << 24) | (g << 16) | (b << 8) | 255


@pytest.mark.slow
def test_recording_shows_what_the_run_was(e2e_run):
    """The blueprint opens on the `frame` timeline at the clip's frame rate, with no α/z plots
    for a run without the four-point target and a text panel saying what the run was; every method
    has a 3-D path; every error series is named and coloured as the report draws it; the recording
    is named after the clip."""
    from pipeline.present.style import method_rgb

    cols, static, reader = read_recording(e2e_run.recording)
    bp = blueprint_columns(reader)
    assert bp["/time_panel"]["TimePanelBlueprint:timeline"][0] == ["frame"]
    assert bp["/time_panel"]["TimePanelBlueprint:fps"][0] == [30.0]
    origins = [o for c in bp.values() for v in c.get("ViewBlueprint:space_origin", []) for o in v]
    assert "/world" in origins and "/run" in origins and not any(o.startswith("/metrics/target") for o in origins)
    assert "/metrics/depth/red" in origins and "/state" in origins  # the ±σ depth tab and the track-state lanes
    assert any("clip" in n for v in cols["/__properties"].get("RecordingInfo:name", []) for n in v)
    # an application per clip: the viewer keeps a blueprint per application, so a batch opened at once
    # (`stereotrack view OUT`) showed every clip in the last one's layout
    (rec,), (blue,) = reader.recordings(), reader.blueprints()
    assert rec.application_id == blue.application_id == "stereotrack: clip"
    assert "# clip" in "".join(t for v in cols["/run"]["TextDocument:text"] for t in v)
    for meth in METHODS:
        assert f"/world/estimates/{meth}/path" in static and cols[f"/world/estimates/{meth}/path"]["LineStrips3D:strips"]
        assert {lab for v in cols[f"/world/estimates/{meth}/points"]["Points3D:labels"] for lab in v} == {"red"}
        tr = e2e_run.estimate.tracks[meth]["red"]
        seen = cols[f"/world/left/estimates/{meth}"]  # a cross (two strips) at each reprojected estimate
        held = [(k, v) for k, v in zip(seen["frame"], seen["LineStrips2D:strips"], strict=True) if v]
        want = e2e_run.estimate.rig.left.project(tr.position[[k for k, _ in held]])
        for (_, (across, upright)), uv in zip(held, want, strict=True):
            np.testing.assert_allclose([np.mean(across, axis=0), np.mean(upright, axis=0)], [uv, uv], atol=1e-3)
        for kind in ("error", "reprojection"):  # one plot per marker, one line per method
            series = cols[f"/metrics/{kind}/red/{meth}"]
            assert series["SeriesLines:names"][0] == [meth]
            assert series["SeriesLines:colors"][0] == [packed(method_rgb(meth))]
    assert "/world/uncertainty/ekf" in cols and "/world/uncertainty/alphabeta" not in cols  # filters' ellipsoids
    truth_z = e2e_run.estimate.truth.positions["red"][:, 2]
    for meth in ("ekf", "kf3d"):  # a filter's signed depth error (mm) with its own σ² for the ±σ band
        tr, band = e2e_run.estimate.tracks[meth]["red"], cols[f"/metrics/depth/red/{meth}"]
        k = np.array(band["frame"])
        np.testing.assert_allclose(np.ravel(band["Measurements:values"]), 1000 * (tr.position[k, 2] - truth_z[k]), rtol=1e-9)
        np.testing.assert_allclose(np.ravel(band["Measurements:variances"]), 1e6 * tr.covariance[k, 2, 2], rtol=1e-9)
        assert band["Measurements:names"][0] == [meth] and len(k) > 30
    assert not any(p.startswith("/metrics/depth/red/") for p in cols if p.split("/")[-1] in ("triangulation", "spsa"))
    for meth in METHODS:  # each track's state lane: a gap without an estimate, "predicting" where it used no measurement
        tr, lane = e2e_run.estimate.tracks[meth]["red"], cols[f"/state/{meth}/red"]
        at = np.searchsorted(lane["frame"], np.arange(len(tr.position)), side="right") - 1
        state = [lane["StateChange:state"][i][0] if i >= 0 else "" for i in at]
        have = np.all(np.isfinite(tr.position), axis=1)
        assert [s == "" for s in state] == (~have).tolist(), meth
        kept = have & (np.array(state) != "restarted")
        assert [s == "predicting" for s in np.array(state)[kept]] == tr.predicted[kept].tolist(), meth
    ell, tr = cols["/world/uncertainty/ekf"], e2e_run.estimate.tracks["ekf"]["red"]
    k = np.array(ell["frame"])
    np.testing.assert_allclose(np.vstack(ell["Ellipsoids3D:centers"]), tr.position[k], atol=1e-6)
    for f, half, q in zip(k, ell["Ellipsoids3D:half_sizes"], ell["Ellipsoids3D:quaternions"], strict=True):
        from scipy.spatial.transform import Rotation  # the 95 % ellipsoid: R diag(half²/χ²₃) Rᵀ = P
        R, h2 = Rotation.from_quat(q[0]).as_matrix(), np.array(half[0]) ** 2 / 7.814727903251178
        np.testing.assert_allclose(R @ np.diag(h2) @ R.T, tr.covariance[f, :3, :3], rtol=1e-4, atol=1e-12)
    hidden = [p for p, c in bp.items() if c.get("EntityBehavior:visible") == [[False]] or
              c.get("EntityBehavior:visible") == [False]]
    assert any("/overrides/world/uncertainty/ekf/" in p for p in hidden), hidden  # shown on one click
    # the best three methods (by the run's own 3-D RMSE) shown in 3-D, the rest one click away
    from pipeline.evaluation.metrics import ranking

    order = [m for m in ranking(e2e_run.estimate.metrics) if m in METHODS]
    tucked = {m for m in METHODS if any(f"/overrides/world/estimates/{m}/" in p for p in hidden)}
    assert tucked == set(order[3:]), (tucked, order)
    plotted_off = {m for m in METHODS if any(f"/overrides/metrics/error/red/{m}" in p for p in hidden)}
    assert plotted_off == set(order[3:]), plotted_off  # the error plots show the same three
    in_camera = {m for m in METHODS if not any(f"/overrides/world/left/estimates/{m}" in p for p in hidden)}
    assert in_camera == {order[0]}, (in_camera, order)  # the camera panes: the best method's crosses only
    # the 3-D eye frames the truth's paths: all of them in view, reaching across most of it
    from pipeline.present.layout import FILL, _project

    eye = next(c for c in bp.values() if "EyeControls3D:look_target" in c)
    target, position = np.ravel(eye["EyeControls3D:look_target"][0]), np.ravel(eye["EyeControls3D:position"][0])
    ndc, depth = _project(np.vstack(list(e2e_run.estimate.truth.positions.values())), position, target)
    assert depth.min() > 0 and np.abs(ndc).max() <= FILL + 1e-6, (ndc.min(axis=0), ndc.max(axis=0))
    assert np.ptp(ndc, axis=0).max() >= 2 * FILL - 0.05, np.ptp(ndc, axis=0)
    # the plotted methods drawn widest first (by name: the viewer's order), so that none hides another
    from pipeline.present.recording import SERIES_WIDTHS

    shown = sorted(order[:3])
    for k, meth in enumerate(shown):
        assert cols[f"/metrics/error/red/{meth}"]["SeriesLines:widths"][-1] == [SERIES_WIDTHS[k]], meth  # the last static


@pytest.mark.slow
def test_the_viewer_dies_with_view(e2e_run, tmp_path):
    """`stereotrack view --web` killed with SIGKILL: the viewer it started ends too."""
    import signal
    import time

    import psutil

    proc = subprocess.Popen([sys.executable, "-m", "pipeline.app.cli", "view", str(e2e_run.clip), "--web", "--port", "9390"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 30
    children = []
    while time.time() < deadline and not children:
        time.sleep(0.3)
        children = psutil.Process(proc.pid).children(recursive=True)
    assert children, "the viewer never started"
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=10)
    _, alive = psutil.wait_procs(children, timeout=5)
    assert not [p for p in alive if p.status() != psutil.STATUS_ZOMBIE]


def test_a_viewer_whose_parent_died_before_the_death_signal_was_armed_never_starts(tmp_path):
    """``terminate_with_parent`` in a child whose parent is already gone (its parent is not the one
    it was started by: killed between the fork and the ``prctl``, so no signal will come) ends the
    child before the program runs. A loaded CI machine left a viewer serving for minutes that way."""
    from functools import partial

    from pipeline.core.lifeline import terminate_with_parent

    ran = tmp_path / "ran"
    code = f"open({str(ran)!r}, 'w').close()"
    gone = subprocess.run([sys.executable, "-c", code], preexec_fn=partial(terminate_with_parent, os.getpid() + 1))
    assert gone.returncode == 1 and not ran.exists()
    alive = subprocess.run([sys.executable, "-c", code], preexec_fn=partial(terminate_with_parent, os.getpid()))
    assert alive.returncode == 0 and ran.exists()


def test_a_track_that_ends_leaves_no_point_behind():
    """The views show the latest batch at the cursor: after a track's last estimate an empty batch
    is logged, and frames before its first and after the empty one log nothing."""
    from pipeline.present.recording import _batches

    nan = [np.nan] * 3
    a = np.array([nan, [0, 0, 1], [0, 0, 2], nan, nan, [0, 0, 5], nan], dtype=float)
    b = np.array([[1, 0, 1], [1, 0, 1], nan, nan, nan, nan, nan], dtype=float)
    got = _batches([a, b], 7)
    assert got.frames.tolist() == [0, 1, 2, 3, 5, 6] and got.lengths.tolist() == [1, 2, 1, 0, 1, 0]
    assert got.which.tolist() == [1, 0, 1, 0, 0]


def h264_copy(src: Path, dst: Path) -> None:
    """``src`` re-encoded as H.264 (PyAV's libx264, near-lossless), as a real camera's footage is."""
    import av
    import cv2

    cap = cv2.VideoCapture(str(src))
    fps = round(cap.get(cv2.CAP_PROP_FPS) or 30)
    with av.open(str(dst), "w") as out:
        stream = out.add_stream("libx264", rate=fps, options={"crf": "12", "preset": "veryfast"})
        ok, frame = cap.read()
        stream.width, stream.height, stream.pix_fmt = frame.shape[1], frame.shape[0], "yuv420p"
        while ok:
            out.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="bgr24")))
            ok, frame = cap.read()
        out.mux(stream.encode())


@pytest.mark.slow
def test_an_h264_clip_is_referenced_not_copied(tmp_path):
    """#41 (video instead of copies): a clip whose cameras are H.264 videos: the recording holds
    each video once (AssetVideo) and a frame reference per frame, at each frame's own video time,
    and no JPEG copy; the same clip in MPEG-4 Part 2 (which the viewer cannot decode) keeps its
    JPEG frames. The recording of the H.264 clip is several times smaller."""
    from rerun import AssetVideo

    from pipeline.app.run import process_clip

    mpeg4, h264 = tmp_path / "mpeg4", tmp_path / "h264"
    shutil.copytree(REPO / "data" / "clips" / "sample_small", mpeg4)
    (mpeg4 / "truth.csv").unlink()  # footage from a real rig: no truth
    shutil.copytree(mpeg4, h264)
    for cam in ("left", "right"):
        h264_copy(mpeg4 / f"{cam}.mp4", h264 / f"{cam}.mp4")
    settings = RunSettings(methods=["triangulation"])
    runs = {c.name: process_clip(c, settings=settings) for c in (mpeg4, h264)}
    cols, static, reader = read_recording(runs["h264"].recording)
    for cam in ("left", "right"):
        assert f"/world/{cam}/image" not in cols and f"/world/{cam}/video" in static
        refs = cols[f"/world/{cam}/video"]
        want = AssetVideo(path=h264 / f"{cam}.mp4").read_frame_timestamps_nanos()
        n = len(want)
        assert refs["frame"][-n:] == list(range(n)) and n == runs["h264"].estimate.n_frames
        got = [v[0] for v in refs["VideoFrameReference:timestamp"] if v]
        assert got == list(want)
    origins = [o for c in blueprint_columns(reader).values() for v in c.get("ViewBlueprint:space_origin", []) for o in v]
    assert not any(o.startswith("/metrics/error") for o in origins)  # no truth: no 3-D error plot to stay empty
    assert any(o.startswith("/metrics/reprojection") for o in origins)
    old, _, _ = read_recording(runs["mpeg4"].recording)
    assert "/world/left/video" not in old and len(old["/world/left/image"]["frame"]) == runs["mpeg4"].estimate.n_frames
    assert runs["h264"].recording.stat().st_size * 2 < runs["mpeg4"].recording.stat().st_size
