"""Nothing lost, nothing stale: no command deletes what stereotrack did not write, batch outputs never
collide, a restart redoes a clip whose inputs changed, one precedence for command line and files,
no traceback on any input (table-driven and property-based), plugins that cannot shadow built-ins,
signals that end every long command cleanly, and clips of one or two frames."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import psutil
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.app.batch import run_batch
from pipeline.app.manifest import MANIFEST, verify_manifest
from pipeline.core.errors import StereotrackError
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from tests.conftest import REPO
from tests.helpers import RED, assert_one_line_error, cli, real_copy, snapshot

SAMPLE = REPO / "data" / "clips" / "sample_small"
FUZZ = settings(max_examples=200, deadline=None, derandomize=True,
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def _quiet_batch(*args, markers=None, **kw):
    settings = RunSettings(methods=["triangulation"], images=False, figures=False, markers=markers)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = run_batch(*args, settings, workers=1, **kw)
    return {o.clip: o.status for o in res}, [str(w.message) for w in caught] + [w for o in res for w in o.warnings]


# ---------------------------------------------------------------------------------------------
# 1. Never delete what stereotrack did not write
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_render_refuses_a_folder_it_did_not_make(tmp_path, monkeypatch, capsys):
    mine = tmp_path / "mydir"
    (mine / "out").mkdir(parents=True)
    (mine / "left").mkdir()
    (mine / "out" / "notes.txt").write_text("precious")
    before = snapshot(mine)
    rc, _, err = cli(monkeypatch, capsys, "render", "default", "-o", mine, "--frames", "2")
    assert rc == 2 and "was not written by stereotrack" in err and str(mine) in err
    assert snapshot(mine) == before
    # an empty folder is fine, and so is re-rendering a clip stereotrack made (other files kept)
    empty = tmp_path / "empty"
    empty.mkdir()
    rc, _, err = cli(monkeypatch, capsys, "render", "default", "-o", empty, "--frames", "2", "--format", "png")
    assert rc == 0, err
    (empty / "my_notes.txt").write_text("mine")
    rc, _, err = cli(monkeypatch, capsys, "render", "default", "-o", empty, "--frames", "3", "--format", "png")
    assert rc == 0, err
    assert (empty / "my_notes.txt").read_text() == "mine" and len(list((empty / "left").iterdir())) == 3


def test_render_never_takes_a_users_scenario_yaml_for_its_mark(tmp_path, monkeypatch, capsys):
    """#40 item 1: a folder holding the user's own scenario.yaml (and their notes in out/) is not a
    clip stereotrack rendered; rendering into it is refused and nothing in it changes."""
    mine = tmp_path / "mine"
    (mine / "out").mkdir(parents=True)
    shutil.copy(REPO / "data" / "scenarios" / "sample_small.yaml", mine / "scenario.yaml")
    (mine / "out" / "notes.txt").write_text("precious")
    before = snapshot(mine)
    rc, _, err = cli(monkeypatch, capsys, "render", mine / "scenario.yaml", "-o", mine, "--frames", "5")
    assert rc == 2 and "was not written by stereotrack" in err and str(mine) in err
    assert snapshot(mine) == before
    (mine / "clip.json").write_text('{"my": "notes"}')  # a clip.json of the user's own is no mark either
    before = snapshot(mine)
    rc, _, err = cli(monkeypatch, capsys, "render", mine / "scenario.yaml", "-o", mine, "--frames", "5")
    assert rc == 2 and "not a clip description stereotrack wrote" in err and snapshot(mine) == before


def test_a_full_disk_names_the_file_and_keeps_nothing_half_written(tmp_path):
    """#40 item 4: a write that fails (ENOSPC, EROFS) is one error naming the file it was writing,
    and neither the file nor its temporary is left."""
    import errno

    from pipeline.core.io import atomic_path

    target = tmp_path / "detections.csv"
    for code in (errno.ENOSPC, errno.EROFS):
        with pytest.raises(StereotrackError, match=r"cannot write \(") as caught, atomic_path(target) as tmp:
            tmp.write_text("half")
            raise OSError(code, os.strerror(code))
        assert str(target) in str(caught.value) and os.strerror(code) in str(caught.value)
        assert list(tmp_path.iterdir()) == []


def test_a_recording_that_does_not_read_back_is_no_output(tmp_path):
    """#40 item 4: rerun's file sink logs a full disk and goes on; the recording is checked with
    rerun's reader before it is moved into place, and a truncated one is an error naming it."""
    import rerun as rr

    from pipeline.present.recording import _check_reads_back

    whole = tmp_path / ".run.partial.rrd"
    rec = rr.RecordingStream("stereotrack")
    rec.save(str(whole))
    for k in range(200):
        rec.set_time("frame", sequence=k)
        rec.log("world/points", rr.Points3D(np.random.default_rng(k).normal(size=(500, 3))))
    rec.flush()
    rec.disconnect()
    _check_reads_back(whole, tmp_path / "run.rrd")  # a complete recording passes
    cut = tmp_path / ".cut.partial.rrd"
    cut.write_bytes(whole.read_bytes()[: whole.stat().st_size // 2])
    with pytest.raises(StereotrackError, match="could not be written completely") as caught:
        _check_reads_back(cut, tmp_path / "run.rrd")
    assert str(tmp_path / "run.rrd") in str(caught.value) and not cut.exists()


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("unshare") is None, reason="needs unshare to mount a small filesystem")
def test_run_on_a_full_disk_is_one_line_naming_the_file(png_clip, tmp_path):
    """#40 item 4 as a user meets it: `run` with out/ on a 2 MB filesystem (a tmpfs in a user and
    mount namespace) ends with one line naming the file that did not fit (here the recording, whose
    sink only logs the full disk), exit 2, and leaves no temporary file and no recording."""
    clip = tmp_path / "clip"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    (clip / "out").mkdir()
    script = (f"mount -t tmpfs -o size=2m tmpfs {clip / 'out'} || exit 77; "
              f"{sys.executable} -m pipeline.app.cli run {clip}; rc=$?; ls -A {clip / 'out'} > {tmp_path / 'left'}; exit $rc")
    done = subprocess.run(["unshare", "-rm", "sh", "-c", script], capture_output=True, text=True, timeout=600)
    if done.returncode == 77:
        pytest.skip("no permission to mount a tmpfs here")
    errors = [ln for ln in done.stderr.splitlines() + done.stdout.splitlines() if ln.startswith("error:")]
    assert done.returncode == 2 and len(errors) == 1, done.stderr[-2000:]
    assert "re_log" not in done.stderr + done.stdout  # rerun's own log lines of the failed sink are not shown
    assert str(clip / "out") in errors[0]
    assert "No space left on device" in errors[0] or "recording could not be written completely" in errors[0]
    left = (tmp_path / "left").read_text().split()
    assert "run.rrd" not in left and not [n for n in left if "partial" in n]


def test_batch_force_never_replaces_a_foreign_folder(tmp_path):
    inp = tmp_path / "in"
    real_copy(inp / "clip")
    (inp / "markers.yaml").write_text(f"- {RED}\n")
    out = tmp_path / "out"
    (out / "clip").mkdir(parents=True)
    (out / "clip" / "thesis.tex").write_text("a user's file")
    status, _ = _quiet_batch(inp, out, force=True)
    assert status == {"clip": "failed"}
    assert (out / "clip" / "thesis.tex").read_text() == "a user's file"
    err = read_csv(out / "summary.csv")["error"][0]
    assert "was not written by stereotrack" in err


# ---------------------------------------------------------------------------------------------
# 2. Output names that cannot collide; 3. a manifest that covers inputs
# ---------------------------------------------------------------------------------------------


@pytest.fixture
def two_same_names(tmp_path) -> tuple[Path, Path]:
    inp = tmp_path / "in"
    real_copy(inp / "a" / "clip")
    real_copy(inp / "b" / "clip")
    (inp / "a" / "clip" / "markers.yaml").write_text(f"- {RED}\n")
    (inp / "b" / "clip" / "markers.yaml").write_text("- blue=#2840e6\n")
    return inp, tmp_path / "out"


def test_batch_outputs_mirror_the_input_tree(two_same_names):
    inp, out = two_same_names
    status, _ = _quiet_batch(inp, out)
    assert status == {"a/clip": "ok", "b/clip": "ok"}
    assert set(read_csv(out / "a" / "clip" / "detections.csv")["marker"]) == {"red"}
    assert set(read_csv(out / "b" / "clip" / "detections.csv")["marker"]) == {"blue"}
    assert verify_manifest(out / "a" / "clip") is None and verify_manifest(out / "b" / "clip") is None
    assert sorted(read_csv(out / "summary.csv")["clip"]) == ["a/clip", "b/clip"]


@pytest.mark.slow
def test_restart_redoes_what_changed_and_says_why(two_same_names):
    inp, out = two_same_names
    _quiet_batch(inp, out)
    assert _quiet_batch(inp, out)[0] == {"a/clip": "skipped", "b/clip": "skipped"}
    # an edited markers.yaml, a replaced video
    (inp / "a" / "clip" / "markers.yaml").write_text(f"markers: [{RED}]\n")
    shutil.copy(SAMPLE / "right.mp4", inp / "b" / "clip" / "left.mp4")
    status, said = _quiet_batch(inp, out)
    assert status == {"a/clip": "ok", "b/clip": "ok"}
    assert any("a/clip: redoing this clip: input markers.yaml changed" in w for w in said), said
    assert any("b/clip: redoing this clip: input left.mp4 changed" in w for w in said), said
    # a root markers.yaml is a setting of every clip without one of its own
    (inp / "markers.yaml").write_text(f"- {RED}\n")
    status, said = _quiet_batch(inp, out)
    assert any("other settings (root_markers)" in w for w in said), said


@pytest.fixture(scope="module")
def batch_done(tmp_path_factory) -> tuple[Path, Path]:
    """(input folder, a batch's complete output folder) to copy and break."""
    inp = tmp_path_factory.mktemp("done") / "in"
    real_copy(inp / "clip")
    (inp / "markers.yaml").write_text(f"- {RED}\n")
    _quiet_batch(inp, inp.parent / "out")
    return inp, inp.parent / "out"


@pytest.mark.slow
@pytest.mark.parametrize("content", ["", "{}", '{"stereotrack": "0.1", "files": {}}', '{"stereotrack": "0.1", "files": []}',
                                     '{"stereotrack": "0.1", "files": {"metrics.json": 3}}', "[1, 2]", "\x00\xff garbage",
                                     '{"files": {"metrics.json": {"size": 1}}}'])
def test_broken_manifest_means_redo_with_a_warning(tmp_path, content, batch_done):
    inp, done = batch_done
    out = tmp_path / "out"
    shutil.copytree(done, out)
    (out / "clip" / MANIFEST).write_bytes(content.encode("utf-8", "surrogateescape"))
    status, said = _quiet_batch(inp, out)
    assert status == {"clip": "ok"}
    assert any("redoing this clip" in w and ("manifest" in w) for w in said), said
    assert verify_manifest(out / "clip") is None


# ---------------------------------------------------------------------------------------------
# 4. One precedence: command line > clip's own file > input root's file > rendered clip's description
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
def test_markers_precedence_in_a_batch(tmp_path):
    inp = tmp_path / "in"
    for name in ("own", "rooted"):
        real_copy(inp / name)
    (inp / "own" / "markers.yaml").write_text("- blue=#2840e6\n")  # the clip's own file
    (inp / "markers.yaml").write_text(f"- {RED}\n")  # the input root's file
    out = tmp_path / "out"
    _quiet_batch(inp, out)
    assert set(read_csv(out / "own" / "detections.csv")["marker"]) == {"blue"}  # own file > root file
    assert set(read_csv(out / "rooted" / "detections.csv")["marker"]) == {"red"}
    # --markers beats both, with a warning naming the clip's own file and both values
    ball = RED.replace("red", "ball")
    _status, said = _quiet_batch(inp, tmp_path / "out2", markers=[ball])
    for name in ("own", "rooted"):
        assert set(read_csv(tmp_path / "out2" / name / "detections.csv")["marker"]) == {"ball"}
    assert any(f"own/markers.yaml: --markers {ball} used instead of this file's blue=#2840e6" in w for w in said), said


def test_calib_units_flag_over_a_declared_unit_warns_naming_both(tmp_path):
    from pipeline.core.calibration import load_calibration, save_calibration

    rig = load_calibration(SAMPLE)
    save_calibration(rig, tmp_path / "calib.yaml", units="mm")
    with pytest.warns(UserWarning, match=r"--calib-units m overrides the unit the file declares \(units: mm\)"):
        forced = load_calibration(tmp_path / "calib.yaml", "m")
    np.testing.assert_allclose(forced.T, rig.T * 1000.0)  # the command line wins, as documented
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(load_calibration(tmp_path / "calib.yaml", "mm").T, rig.T)  # agreeing: silent


def test_clip_description_is_last(tmp_path, png_clip):
    """A rendered clip's own colours apply only when nothing else names the markers."""
    from detectors.stage import detect_clip

    clip = tmp_path / "clip"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    res = detect_clip(clip, out_dir=tmp_path / "o1")
    assert set(res.marker_colours) == {"red", "green", "blue"}
    (clip / "markers.yaml").write_text("- green=#1ec828\n")
    assert set(detect_clip(clip, out_dir=tmp_path / "o2").marker_colours) == {"green"}


# ---------------------------------------------------------------------------------------------
# 5. No traceback on any input: the eleven of the report, then every parser fuzzed
# ---------------------------------------------------------------------------------------------


def _calib_image_size(clip: Path) -> None:
    text = (clip / "calib.yaml").read_text()
    (clip / "calib.yaml").write_text(text.replace("image_width: 320\nimage_height: 240\n", "image_size: [ 320 ]\n"))


def _raising_plugin(monkeypatch) -> None:
    from pipeline.estimators import registration as base
    from pipeline.estimators.triangulation import TriangulationEstimator

    class Boom(TriangulationEstimator):
        name = "boom"

        def _step(self, obs):
            if self.frame == 7:
                raise ValueError("the plugin's own bug")
            return super()._step(obs)

    Boom.__module__, Boom.__qualname__ = "my_plugin.boom", "Boom"
    monkeypatch.setitem(base.REGISTRY, "boom", Boom)


def _estimates_without_x(tmp: Path, clip: Path, monkeypatch) -> None:
    """An estimate stage's outputs whose ekf.csv lost its x column (edited by hand, say)."""
    (clip / "out" / "estimates").mkdir(parents=True, exist_ok=True)
    (clip / "out" / "metrics.json").write_text('{"frames": 1, "methods": {"ekf": {}}}')
    (clip / "out" / "estimates" / "ekf.csv").write_text("frame,t,marker,y,z\n0,0,red,0.1,2.0\n")


TRACEBACKS = {
    # name: (setup(tmp, clip, monkeypatch) or None, argv (formatted with {clip}, {tmp}), exit code, text on stderr)
    "run --frames -5": (None, ["run", "default", "--frames", "-5", "-o", "{tmp}/r"], 2,
                        "frames: Input should be greater than 0"),
    "run --seed -1": (None, ["run", "default", "--seed", "-1", "-o", "{tmp}/r"], 2, "seed: Input should be greater"),
    "run on a single video": (None, ["run", "{clip}/left.mp4"], 2, "left.mp4: is a single video"),
    "--config with .inf": (lambda t, c, m: (t / "cfg.yaml").write_text("ekf: {process_noise: .inf}\n"),
                           ["estimate", "{clip}", "--config", "{tmp}/cfg.yaml"], 2,
                           "ekf.process_noise: Input should be a finite"),
    "--config binary": (lambda t, c, m: (t / "cfg.yaml").write_bytes(bytes(range(256))),
                        ["estimate", "{clip}", "--config", "{tmp}/cfg.yaml"], 2, "cfg.yaml: not a text file"),
    "one-element image_size": (lambda t, c, m: _calib_image_size(c), ["estimate", "{clip}"], 2,
                               "field 'image_size' must be [width, height]"),
    "garbage --scheduler-file": (lambda t, c, m: (t / "s.json").write_text("garbage"),
                                 ["batch", "{clip}", "-o", "{tmp}/b", "--scheduler-file", "{tmp}/s.json", "--markers", RED],
                                 2, "s.json: not a Dask scheduler file"),
    "scheduler file without address": (lambda t, c, m: (t / "s.json").write_text('{"id": 1}'),
                                       ["batch", "{clip}", "-o", "{tmp}/b", "--scheduler-file", "{tmp}/s.json"],
                                       2, "no scheduler 'address'"),
    "plugin whose step raises": (lambda t, c, m: _raising_plugin(m), ["estimate", "{clip}", "--methods", "boom"], 2,
                                 "plugin method (my_plugin.boom.Boom) 'boom' raised ValueError: the plugin's own bug "
                                 "(marker 'red', frame 7)"),
    "duplicate marker names": (None, ["detect", "{clip}", "--markers", f"{RED},red=#2840e6"], 2,
                               "marker name 'red' is given twice"),
    "corrupt metrics.json for report": (lambda t, c, m: (c / "out" / "metrics.json").write_text("{nope"),
                                        ["report", "{clip}"], 2, "metrics.json: unreadable metrics (not JSON"),
    "estimates CSV without x, for report": (_estimates_without_x, ["report", "{clip}"], 2,
                                            "ekf.csv: missing column(s) x"),
    "clip.json that is a list": (lambda t, c, m: (c / "clip.json").write_text("[]"), ["estimate", "{clip}"], 2,
                                 "clip.json: unreadable clip description"),
}


@pytest.mark.parametrize("case", list(TRACEBACKS))
def test_former_tracebacks_are_one_line(case, detected_clip, tmp_path, monkeypatch, capsys):
    setup, argv, code, text = TRACEBACKS[case]
    clip = tmp_path / "clip"
    shutil.copytree(detected_clip, clip)
    if setup is not None:
        setup(tmp_path, clip, monkeypatch)
    before = snapshot(clip)
    rc, out, err = cli(monkeypatch, capsys, *[a.format(clip=clip, tmp=tmp_path) for a in argv])
    assert_one_line_error(rc, out, err, text, code, case)
    assert snapshot(clip) == before, case


def _fails_cleanly(fn, path: Path | None = None) -> None:
    """``fn()`` succeeds, or raises a StereotrackError naming ``path`` in one line."""
    try:
        fn()
    except StereotrackError as exc:
        assert "\n" not in str(exc)
        if path is not None:
            assert str(path) in str(exc), str(exc)


TEXT = st.text(st.characters(codec="utf-8"), max_size=60)
SPEC_CHARS = st.text(st.sampled_from("abcRED_-@:=#,0123456789fF"), max_size=25)


@FUZZ
@given(spec=st.one_of(TEXT, SPEC_CHARS))
def test_fuzz_marker_specs(spec):
    from detectors.blob import MarkerColor

    _fails_cleanly(lambda: MarkerColor.parse(spec))
    _fails_cleanly(lambda: MarkerColor.parse_window(spec))


def _containers(kids: st.SearchStrategy) -> st.SearchStrategy:
    return st.one_of(st.lists(kids, max_size=4), st.dictionaries(TEXT, kids, max_size=4))


YAMLISH = st.recursive(st.none() | st.booleans() | st.integers(-10**6, 10**6) | st.floats(allow_nan=True) | TEXT,
                       _containers, max_leaves=12)


def _write_yaml_or_bytes(path: Path, data, raw: bytes | None) -> None:
    import yaml

    if raw is not None:
        path.write_bytes(raw)
    else:
        path.write_text(yaml.safe_dump(data, allow_unicode=True))


@FUZZ
@given(data=st.one_of(YAMLISH, st.lists(SPEC_CHARS, max_size=4), st.fixed_dictionaries({"markers": YAMLISH})),
       raw=st.none() | st.binary(max_size=80))
def test_fuzz_markers_yaml(tmp_path, data, raw):
    from detectors.markers import read_markers_file

    path = tmp_path / "markers.yaml"
    _write_yaml_or_bytes(path, data, raw)
    _fails_cleanly(lambda: read_markers_file(path), path)


METHOD_FIELDS = st.dictionaries(st.sampled_from(["process_noise", "pixel_sigma", "init", "seed", "alpha", "beta", "x"]),
                                YAMLISH, max_size=3)


@FUZZ
@given(data=st.one_of(YAMLISH, st.dictionaries(st.sampled_from(["ekf", "spsa", "kf3d", "nope"]), METHOD_FIELDS | YAMLISH,
                                               max_size=3)),
       raw=st.none() | st.binary(max_size=80))
def test_fuzz_method_config(tmp_path, data, raw):
    from pipeline.estimators.configs import load_method_configs

    path = tmp_path / "cfg.yaml"
    _write_yaml_or_bytes(path, data, raw)
    _fails_cleanly(lambda: load_method_configs(path), path)


SCENARIO_KEYS = ["name", "frames", "fps", "seed", "rig", "render", "objects", "distractors", "width", "baseline", "motion",
                 "type", "start", "velocity", "color", "radius", "focal"]
SCENARIO_ISH = st.recursive(st.none() | st.integers(-5, 10**5) | st.floats(allow_nan=True) | TEXT | st.sampled_from(
    ["constant_velocity", "sinusoid", "four_point_target"]),
    lambda kids: st.lists(kids, max_size=4) | st.dictionaries(st.sampled_from(SCENARIO_KEYS), kids, max_size=5),
    max_leaves=20)


@FUZZ
@given(data=st.dictionaries(st.sampled_from(SCENARIO_KEYS), SCENARIO_ISH, max_size=6), raw=st.none() | st.binary(max_size=80))
def test_fuzz_scenario_yaml(tmp_path, data, raw):
    from renderers.scenario import load_scenario

    path = tmp_path / "scen.yaml"
    _write_yaml_or_bytes(path, data, raw)
    _fails_cleanly(lambda: load_scenario(path), path)


STAMP_CELL = st.one_of(st.integers(-3, 40), st.integers(10**8, 10**10), st.floats(allow_nan=True, allow_infinity=True),
                       st.sampled_from(["left", "right", "centre", "", "1e400", "0x10"]), TEXT)


@FUZZ
@given(rows=st.lists(st.tuples(STAMP_CELL, st.sampled_from(["left", "right"]) | TEXT, STAMP_CELL), max_size=12),
       header=st.sampled_from([["frame", "camera", "t"], ["frame", "camera"], ["t", "camera", "frame"], ["a"]]),
       raw=st.none() | st.binary(max_size=80))
def test_fuzz_timestamps(tmp_path, rows, header, raw):
    """#40 (acceptance): timestamps.csv of any content reads, or fails in one line naming it."""
    from pipeline.core.timestamps import read_timestamps

    path = _csv_or_bytes(tmp_path / "timestamps.csv", [header, *rows], raw)
    _fails_cleanly(lambda: read_timestamps(path), path)


def _csv_or_bytes(path: Path, rows: list, raw: bytes | None) -> Path:
    """``raw`` written as it is, else ``rows`` as a CSV table."""
    import csv

    if raw is not None:
        path.write_bytes(raw)
    else:
        with open(path, "w", newline="") as fh:
            csv.writer(fh).writerows(rows)
    return path


CALIB_TEXT = (SAMPLE / "calib.yaml").read_text()


@FUZZ
@given(cut=st.integers(0, len(CALIB_TEXT)), length=st.integers(0, 40), insert=st.text(st.sampled_from(" :[],.-0123456789"
                                                                                                   "\nabcKDRTnimage_size"),
                                                                                   max_size=20),
       raw=st.none() | st.binary(max_size=200))
def test_fuzz_calibration(tmp_path, cut, length, insert, raw):
    from pipeline.core.calibration import load_calibration

    path = tmp_path / "calib.yaml"
    if raw is not None:
        path.write_bytes(raw)
    else:
        path.write_text(CALIB_TEXT[:cut] + insert + CALIB_TEXT[cut + length:])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        _fails_cleanly(lambda: load_calibration(path), path)


CSV_CELL = st.one_of(st.sampled_from(["", "nan", "inf", "-1", "0", "3", "1e400", "left", "right", "red", "x"]),
                     st.floats(allow_nan=True).map(str), TEXT.filter(lambda s: "\n" not in s and "\r" not in s))


@FUZZ
@given(rows=st.lists(st.lists(CSV_CELL, max_size=8), max_size=6), header=st.booleans(), raw=st.none() | st.binary(max_size=80))
def test_fuzz_detection_csv(tmp_path, rows, header, raw):
    from pipeline.core.clip import DETECTION_COLUMNS
    from pipeline.core.detections import load_detections

    path = _csv_or_bytes(tmp_path / "detections.csv", [DETECTION_COLUMNS, *rows] if header else rows, raw)
    _fails_cleanly(lambda: load_detections(path, 40), path)


@FUZZ
@given(data=st.one_of(YAMLISH, st.fixed_dictionaries({"stereotrack": TEXT, "files": YAMLISH, "inputs": YAMLISH,
                                                      "settings": YAMLISH})),
       raw=st.none() | st.binary(max_size=80))
def test_fuzz_manifest(tmp_path, data, raw):
    folder = tmp_path / "clipout"
    folder.mkdir(exist_ok=True)
    (folder / "metrics.json").write_text("{}")
    (folder / MANIFEST).write_bytes(raw if raw is not None else json.dumps(data).encode())
    why = verify_manifest(folder, {"detector": "blob"}, {"left.mp4": SAMPLE / "left.mp4"})
    assert why is None or isinstance(why, str)


@FUZZ
@given(data=st.one_of(YAMLISH, st.fixed_dictionaries({"address": TEXT})), raw=st.none() | st.binary(max_size=80))
def test_fuzz_scheduler_file(tmp_path, data, raw):
    from pipeline.app.batch import _checked_scheduler_file

    path = tmp_path / "scheduler.json"
    path.write_bytes(raw if raw is not None else json.dumps(data).encode())
    _fails_cleanly(lambda: _checked_scheduler_file(path), path)


# ---------------------------------------------------------------------------------------------
# 6. Plugins and names
# ---------------------------------------------------------------------------------------------


def test_plugin_cannot_shadow_a_builtin(monkeypatch):
    from pipeline.estimators import register
    from pipeline.estimators import registration as base
    from pipeline.estimators.ekf import EKFEstimator
    from pipeline.estimators.triangulation import TriangulationEstimator

    monkeypatch.setattr(base, "REGISTRY", dict(base.REGISTRY))

    class FakeEKF(TriangulationEstimator):
        name = "ekf"

    FakeEKF.__module__, FakeEKF.__qualname__ = "someone_else.plugin", "FakeEKF"
    with pytest.warns(UserWarning, match=r"someone_else.plugin.FakeEKF is named 'ekf'.*the built-in is kept"):
        register(FakeEKF)
    assert base.REGISTRY["ekf"] is EKFEstimator


# ---------------------------------------------------------------------------------------------
# 7. Signals: SIGTERM and SIGINT end run, batch and render-batch cleanly
# ---------------------------------------------------------------------------------------------


def _until(cond, timeout: float = 90.0) -> bool:
    deadline = time.time() + timeout
    while time.time() < deadline:
        if cond():
            return True
        time.sleep(0.02)
    return False


def _partials(folder: Path) -> list[Path]:
    return [p for p in folder.rglob("*") if ".partial" in p.name] if folder.exists() else []


SIGNAL_CASES = {
    "batch": (lambda t: ["batch", str(_batch_input(t)), "-o", str(t / "out"), "--workers", "2", "--methods",
                         "triangulation,ekf", "--no-images"], lambda t: t / "out"),
    "run": (lambda t: ["run", str(shutil.copytree(SAMPLE, t / "clip")), "--methods", "triangulation,ekf"],
            lambda t: t / "clip" / "out"),
    "render-batch": (lambda t: ["render-batch", "default", "--seeds", "0..2", "--frames", "600", "-o", str(t / "rb"),
                                "--workers", "2"], lambda t: t / "rb"),
}


def _batch_input(t: Path) -> Path:
    for i in range(3):
        real_copy(t / "in" / f"c{i}")
    (t / "in" / "markers.yaml").write_text(f"- {RED}\n")
    return t / "in"


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
@pytest.mark.parametrize("command", list(SIGNAL_CASES))
def test_signal_ends_cleanly(command, sig, tmp_path):
    argv, watched = SIGNAL_CASES[command]
    args, out = argv(tmp_path), watched(tmp_path)
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.app.cli", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, cwd=tmp_path)
    busy = (lambda: bool(_partials(out))) if command != "run" else (lambda: (out / "detections.csv").exists()
                                                                        or bool(_partials(out)))
    assert _until(lambda: proc.poll() is not None or busy()), "never got busy"
    assert proc.poll() is None, proc.communicate()[1]
    family = psutil.Process(proc.pid).children(recursive=True)
    proc.send_signal(sig)
    _out, err = proc.communicate(timeout=60)
    assert proc.returncode == 128 + sig, err
    lines = [line for line in err.splitlines() if line.startswith("interrupted")]
    assert lines == [f"interrupted ({sig.name}): stopped; nothing half-written was kept"], err
    assert "Traceback" not in err and "leaked semaphore" not in err  # #40 item 10: the resource tracker's lines
    _gone, alive = psutil.wait_procs(family, timeout=3)
    assert not [p for p in alive if p.is_running() and p.status() != psutil.STATUS_ZOMBIE]
    assert not _partials(out), _partials(out)
    assert not (out / ".stereotrack.lock").exists()


LOST_INTERRUPT = """
import signal, sys
import pipeline.core.interrupts as interrupts
import renderers.motion, renderers.render
truth = renderers.motion.simulate_truth
def lost(scenario):  # the handler ran, and its KeyboardInterrupt was swallowed inside a library
    interrupts._received = signal.SIGTERM
    return truth(scenario)
renderers.render.simulate_truth = lost
sys.argv = ["stereotrack", *sys.argv[1:]]
from pipeline.app.cli import main
main()
"""


@pytest.mark.parametrize("workers", [1, 2])
def test_a_signal_whose_interrupt_a_library_swallowed_still_ends_the_command(workers, tmp_path):
    """A KeyboardInterrupt raised inside a C extension's import can be lost (numpy.random, loaded
    lazily, swallowed 2 of 200 signals sent as it loaded; a render-batch then rendered every clip
    and exited 0): the command still stops at its next commit or progress tick, commits nothing."""
    out = tmp_path / "rb"
    res = subprocess.run([sys.executable, "-c", LOST_INTERRUPT, "render-batch", "default", "--seeds", "0..2",
                          "--frames", "30", "-o", str(out), "--workers", str(workers)],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert res.returncode == 128 + signal.SIGTERM, res.stderr
    assert "interrupted (SIGTERM): stopped; nothing half-written was kept" in res.stderr
    assert not [p for p in out.rglob("*") if p.is_file()], list(out.rglob("*"))


# ---------------------------------------------------------------------------------------------
# 8. Edge clips
# ---------------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(("frames", "fmt"), [(1, "mp4"), (1, "png"), (2, "mp4")])
def test_one_and_two_frame_clips_run_end_to_end(frames, fmt, tmp_path):
    clip = tmp_path / "edge"
    env = {**os.environ, "COLUMNS": "200"}
    res = subprocess.run([sys.executable, "-m", "pipeline.app.cli", "run", "default", "--frames", str(frames), "--format", fmt,
                          "-o", str(clip)], capture_output=True, text=True, cwd=tmp_path, env=env, timeout=300)
    assert res.returncode == 0, res.stderr
    assert "warning" not in res.stderr.lower(), res.stderr  # no numpy noise ("Mean of empty slice")
    metrics = json.loads((clip / "out" / "metrics.json").read_text())
    assert metrics["frames"] == frames
    tri = metrics["methods"]["triangulation"]
    assert tri["frames"] >= frames and tri["rmse"] < 0.01
    spsa = metrics["methods"]["spsa_stereo"]
    if frames == 1:
        assert spsa["note"] == "needs at least 2 frames; this clip has 1: no estimate"
        assert "**spsa_stereo**: needs at least 2 frames" in (clip / "out" / "report.md").read_text()
    else:
        assert "note" not in spsa and spsa["rmse"] is not None


def test_library_warnings_name_their_source(capsys):
    from pipeline.app.cli import _show_warning

    _show_warning(RuntimeWarning("Mean of empty slice"), RuntimeWarning, "/x/numpy/lib/_nanfunctions_impl.py", 1215)
    _show_warning(UserWarning("clip/calib.yaml: something"), UserWarning, str(REPO / "pipeline" / "camera.py"), 10)
    err = capsys.readouterr().err.splitlines()
    assert err == ["warning: _nanfunctions_impl.py:1215: RuntimeWarning: Mean of empty slice",
                   "warning: clip/calib.yaml: something"]


@pytest.mark.parametrize(("field", "value"), [(("rig", "distortion"), [float("nan"), 0.0, 0.0, 0.0, 0.0]),
                                              (("rig", "sync_offset_s"), float("inf")),
                                              (("distractors", 0, "position"), [0.0, float("nan"), 1.0])])
def test_nan_or_inf_in_a_scenario_is_an_error_naming_the_field(field, value):
    """#40 item 8: NaN or inf passed validation and ended in an internal error; now one line."""
    from pipeline.core.errors import ScenarioError
    from renderers.scenario import load_scenario, parse_scenario

    data = load_scenario("multi_marker").model_dump(mode="json")
    node = data
    for key in field[:-1]:
        node = node[key]
    node[field[-1]] = value
    name = ".".join(str(k) for k in field)
    with pytest.raises(ScenarioError, match=rf"my\.yaml: invalid scenario: {name}.*finite number"):
        parse_scenario(data, "my.yaml")


@pytest.mark.parametrize("square", ["25", "1", "0.5"])
def test_a_square_without_a_unit_that_cannot_be_metres_is_refused(square):
    """#40 item 3: `--square 25` was 25 m, silently (a 300 m baseline, exit 0)."""
    from pipeline.calibrate import parse_length

    with pytest.raises(StereotrackError, match=rf"--square {square} has no unit and would be .* metres: give one"):
        parse_length(square)
    assert parse_length("0.024") == 0.024 and parse_length("25mm") == pytest.approx(0.025)


def test_a_clip_whose_cameras_both_drop_the_last_frames_runs(tmp_path):
    """#40 item 7: with drop rate 0.5, seed 2, both cameras drop frame 19 of 20; the run stopped
    with "truth.csv: line 40: frame 19 is outside the clip's frames 0..18", blaming a file the
    renderer wrote. The clip's own frame count (clip.json) now bounds its truth."""
    from pipeline.app.run import process_clip
    from renderers.render import render_clip
    from renderers.scenario import load_scenario, parse_scenario
    from renderers.truth import frame_times

    data = load_scenario("sample_small").model_dump(mode="json")
    data["rig"]["drop_rate"], data["seed"], data["frames"] = 0.5, 2, 20
    scenario = parse_scenario(data)
    assert not frame_times(scenario).present[:, -1].any()  # the case: every camera dropped the last frame
    render_clip(scenario, tmp_path / "clip", fmt="png", workers=1)
    res = process_clip(tmp_path / "clip", settings=RunSettings(methods=("triangulation", "ekf"), images=False,
                                                                recording=False, figures=False))
    assert res.estimate.metrics["frames"] == 20 and res.estimate.metrics["methods"]["triangulation"]["rmse"] < 0.2


def test_a_frame_rate_contradicting_the_clip_s_frame_times_is_warned_naming_both(tmp_path):
    """#40 item 6: `--fps` against timestamps.csv re-gridded the clip with no word naming the two."""
    from pipeline.core.clip import Clip
    from renderers.render import render_clip
    from renderers.scenario import load_scenario

    render_clip(load_scenario("sample_small").with_overrides(frames=6), tmp_path / "clip", fmt="png", workers=1)
    with pytest.warns(UserWarning, match=r"--fps 60 contradicts timestamps.csv's frame times \(30 fps\); using 60"):
        assert Clip(tmp_path / "clip", fps=60).fps == 60
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert Clip(tmp_path / "clip", fps=30).fps == 30  # agreeing: no warning


def test_run_on_a_clip_folder_refuses_an_output_it_would_ignore(tmp_path, monkeypatch):
    """`run CLIP -o DIR` wrote CLIP/out and ignored -o without a word (and a folder in the working
    directory named like a built-in scenario is that clip, not the scenario)."""
    from typer.testing import CliRunner

    from pipeline.app.cli import app

    (tmp_path / "identical").mkdir()
    (tmp_path / "identical" / "left.mp4").write_bytes(b"")
    monkeypatch.chdir(tmp_path)
    res = CliRunner().invoke(app, ["run", "identical", "-o", str(tmp_path / "elsewhere")])
    assert res.exit_code != 0 and "-o sets where a rendered clip goes; identical is a clip folder" in str(res.exception)
    assert not (tmp_path / "elsewhere").exists() and not (tmp_path / "identical" / "out").exists()


def test_calibrate_never_replaces_a_calibration_it_did_not_write(tmp_path):
    """#40 item 2: `calibrate` replaced an existing calib.yaml (a user's own) without a word. Now:
    refused before any work, the file untouched; `calibrate`'s own output (its report beside it)
    is replaced as before, and --force replaces anything."""
    from pipeline.calibrate import calibrate_folder, check_replaceable_calibration
    from pipeline.core.board import Board

    mine = tmp_path / "calib.yaml"
    mine.write_text("%YAML:1.0\nK1: precious\n")
    with pytest.raises(StereotrackError, match=r"calib\.yaml: exists and was not written by `stereotrack calibrate`"):
        calibrate_folder(tmp_path / "no-such-folder", Board("chessboard", 9, 6, 0.025), mine)
    assert mine.read_text() == "%YAML:1.0\nK1: precious\n"
    check_replaceable_calibration(mine, force=True)
    (tmp_path / "calib_report.md").write_text("# Calibration report: calib.yaml\n")
    check_replaceable_calibration(mine)  # stereotrack's own output: replaceable


def _stamps(tmp_path, rows: list[tuple[int, str, float]]):
    from pipeline.core.io import write_csv

    path = tmp_path / "timestamps.csv"
    write_csv(path, ["frame", "camera", "t"], rows)
    return path


GOOD_STAMPS = [(k, cam, k / 30 + (0.004 if cam == "right" else 0.0)) for k in range(30) for cam in ("left", "right")]


@pytest.mark.parametrize(("case", "rows", "problem"), [
    ("milliseconds", [(k, c, 1000 * t) for k, c, t in GOOD_STAMPS], r"frames are 33\.3+ apart: t must be in seconds"),
    ("two times swapped", [(k, c, (GOOD_STAMPS[2 * (k ^ 1 if k in (10, 11) else k)][2] if c == "left" else t))
                           for k, c, t in GOOD_STAMPS], r"line \d+: left frame 11 at .* is not after frame 10"),
    ("a row twice", [*GOOD_STAMPS[:40], GOOD_STAMPS[39], *GOOD_STAMPS[40:]], r"line 42: right frame 19 is listed twice"),
    ("frame 10⁹", [*GOOD_STAMPS[:-2], (10**9, "left", 2.0), GOOD_STAMPS[-1]], r"left frame 1000000000 is far beyond"),
])
def test_timestamps_are_checked_not_taken_on_trust(tmp_path, case, rows, problem):
    """#40 item 5: milliseconds made a 29,060-frame grid, swapped times and a duplicated row gave
    wrong numbers silently, a frame number of 10⁹ tried to allocate 29.8 GiB."""
    from pipeline.core.timestamps import read_timestamps

    path = _stamps(tmp_path, rows)
    with pytest.raises(StereotrackError, match=problem) as err:
        read_timestamps(path)
    assert str(err.value).startswith(f"{path}: ") and "\n" not in str(err.value)
    read_timestamps(_stamps(tmp_path, GOOD_STAMPS))  # the file as it should be reads


@pytest.mark.parametrize(("case", "problem"), [
    ("footage longer", "timestamps.csv: has no time for left frame 20 (4 of the footage's 24 frames have none)"),
    ("footage shorter", "timestamps.csv: lists left frame 24 but the left footage has 24 frames (0–23): footage "
                        "shorter than its timestamps"),
])
def test_footage_and_its_timestamps_must_agree(mp4_clip, tmp_path, monkeypatch, capsys, case, problem):
    """#40 item 5: a video shorter than its timestamps ran on (errors growing to 667 mm, exit 0) and
    footage longer than them was an internal error. Both are one line naming timestamps.csv, exit 2."""
    from pipeline.core.io import read_csv, write_csv

    clip = tmp_path / "clip"
    shutil.copytree(mp4_clip, clip, ignore=shutil.ignore_patterns("out"))
    shutil.copy(clip / "timestamps.csv", tmp_path / "good.csv")
    ts = read_csv(clip / "timestamps.csv", ["frame", "camera", "t"])
    rows = list(zip(ts["frame"].astype(int), ts["camera"], ts["t"], strict=True))
    if case == "footage longer":
        rows = [r for r in rows if r[0] < 20]
    else:
        rows += [(24 + j, cam, 0.8 + j / 30 + 1e-3 * (cam == "right")) for cam in ("left", "right") for j in range(4)]
    write_csv(clip / "timestamps.csv", ["frame", "camera", "t"], rows)
    rc, out, err = cli(monkeypatch, capsys, "detect", clip)
    assert_one_line_error(rc, out, err, problem, case=case)
    shutil.copy(tmp_path / "good.csv", clip / "timestamps.csv")  # the clip as it was rendered runs
    rc, _, err = cli(monkeypatch, capsys, "detect", clip)
    assert rc == 0, err


@pytest.mark.parametrize("command", ["detect", "estimate", "report", "export"])
def test_an_output_folder_of_the_user_s_is_never_written_into(tmp_path, command):
    """#40 item 2: `detect/estimate/report/export -o` replaced a user's files of the same names.
    A folder given with -o must be new, empty or stereotrack's; a user's is refused, untouched."""
    from typer.testing import CliRunner

    from pipeline.app.cli import app

    clip = shutil.copytree(SAMPLE, tmp_path / "clip")
    runner = CliRunner()
    assert runner.invoke(app, ["run", str(clip), "--methods", "triangulation"]).exit_code == 0
    mine = tmp_path / "mine"
    mine.mkdir()
    for name in ("detections.csv", "metrics.json", "report.md", "triangulation.trc", "notes.txt"):
        (mine / name).write_text("precious\n")
    before = {p.name: p.read_text() for p in mine.iterdir()}
    res = runner.invoke(app, [command, str(clip), "-o", str(mine)])
    assert res.exit_code != 0 and "was not written by stereotrack" in str(res.exception)
    assert {p.name: p.read_text() for p in mine.iterdir()} == before
    fresh = tmp_path / "fresh"
    for _ in range(2):  # a new folder, then the same folder again: stereotrack's own, replaced
        res = runner.invoke(app, [command, str(clip), "-o", str(fresh)])
        assert res.exit_code == 0, res.output


@pytest.mark.parametrize("command", ["detect", "estimate", "report", "export"])
def test_single_stages_wait_for_no_run_holding_the_clip(detected_clip, tmp_path, monkeypatch, capsys, command):
    """#40 item 10: `estimate`, `detect`, `report` and `export` took no lock while `run` held the
    clip's out/. Now each fails at once naming the holder, and changes nothing there."""
    from pipeline.core.lifeline import OutputLock

    clip = tmp_path / "clip"
    shutil.copytree(detected_clip, clip)
    (clip / "out" / "report.md").write_text("# an earlier report\n")
    before = snapshot(clip)
    with OutputLock(clip / "out", f"stereotrack run {clip}"):
        rc, out, err = cli(monkeypatch, capsys, command, clip)
    assert_one_line_error(rc, out, err, f"output folder is in use by stereotrack run {clip}", case=command)
    assert snapshot(clip) == before


def test_export_leaves_out_the_estimates_an_earlier_estimate_left(detected_clip, tmp_path, monkeypatch, capsys):
    """#40 item 10: `export` wrote the tables of an earlier `estimate` that the last one (and so the
    reports) no longer has; it now exports the last estimate's methods, and naming a stale one is
    an error saying why."""
    clip = tmp_path / "clip"
    shutil.copytree(detected_clip, clip)
    assert cli(monkeypatch, capsys, "estimate", clip, "--methods", "triangulation,kf3d")[0] == 0
    assert cli(monkeypatch, capsys, "estimate", clip, "--methods", "triangulation")[0] == 0
    assert (clip / "out" / "estimates" / "kf3d.csv").exists()  # the earlier table is still there, untouched
    rc, out, err = cli(monkeypatch, capsys, "export", clip)
    assert rc == 0, err
    assert sorted(p.name for p in (clip / "out" / "export").glob("*.trc")) == ["triangulation.trc"]
    rc, out, err = cli(monkeypatch, capsys, "export", clip, "--methods", "kf3d")
    assert_one_line_error(rc, out, err, "the estimates of 'kf3d' are from an earlier estimate")


def test_a_marker_its_colour_range_misses_is_warned(png_clip, tmp_path, monkeypatch, capsys):
    """#40 item 10: a colour range that finds its marker in almost no frame ran to a full table of
    dashes without a word. Now a warning per camera names the marker and the count, and detect.json
    keeps it as a failed check."""
    clip = tmp_path / "clip"
    shutil.copytree(png_clip, clip, ignore=shutil.ignore_patterns("out"))
    rc, _, err = cli(monkeypatch, capsys, "detect", clip, "--markers", "red=#e62828", "--markers", "yellow=#e6d214")
    assert rc == 0, err
    for cam in ("left", "right"):
        assert f"marker 'yellow' found in 0 of 24 {cam} frames" in err
    assert "marker 'red'" not in err
    checks = json.loads((clip / "out" / "detect.json").read_text())["checks"]
    assert [c["subject"] for c in checks if c["name"] == "detection_rate" and not c["ok"]] == ["yellow", "yellow"]


@pytest.mark.parametrize(("case", "expected"), [
    ("metres for millimetres", "cameras 300 m apart: is the calibration in the unit it states"),
    ("focal of another lens", "the left camera's focal length 3e+04 px is 93.8× the image width 320 px"),
])
def test_an_implausible_calibration_is_a_failed_check(detected_clip, tmp_path, monkeypatch, capsys, case, expected):
    """#40 (build): `--square 25` made a 300 m baseline and `run` reported a 3-D RMSE of 2,166,929 mm
    under "All input checks passed". A calibration whose cameras are hundreds of metres apart, or
    whose focal length no lens of that image could have, is a failed check naming the file."""
    from dataclasses import replace

    from pipeline.core.calibration import load_calibration, save_calibration
    from pipeline.core.camera import Camera

    clip = tmp_path / "clip"
    shutil.copytree(detected_clip, clip)
    rig = load_calibration(clip / "calib.yaml")
    if case == "metres for millimetres":
        bad = replace(rig, right=Camera(rig.right.K, rig.right.R, rig.right.t * 300 / np.linalg.norm(rig.right.t),
                                        rig.right.D))
    else:
        K = rig.left.K.copy()
        K[0, 0] = K[1, 1] = 30_000.0
        bad = replace(rig, left=Camera(K, rig.left.R, rig.left.t, rig.left.D))
    save_calibration(bad, clip / "calib.yaml")
    rc, _, err = cli(monkeypatch, capsys, "estimate", clip, "--methods", "triangulation")
    assert rc == 0, err
    assert expected in err, err
    rc, _, err = cli(monkeypatch, capsys, "report", clip)
    assert rc == 0, err
    assert "All input checks passed" not in (clip / "out" / "report.md").read_text()


def test_a_sink_that_stops_writing_is_reported_not_waited_on(tmp_path):
    """pipeline.present.sink.flushed: a stream whose flush keeps timing out while its file does not grow
    is given up after ``stalled_s`` (rerun's own flush would wait for ever on a full disk) and defused;
    one that flushes is not; one whose file still grows is waited on."""
    from pipeline.present.sink import flushed

    class Stuck:
        def __init__(self, grow: Path | None = None, after: int = 10**9) -> None:
            self.calls, self.grow, self.after = 0, grow, after

        def flush(self, timeout_sec: float) -> None:
            self.calls += 1
            if self.grow is not None:
                with open(self.grow, "ab") as fh:
                    fh.write(b"x")
            if self.calls < self.after:
                raise RuntimeError("flush timed out")

    f = tmp_path / "run.rrd"
    f.write_bytes(b"abc")
    stuck = Stuck()
    assert not flushed(stuck, f, stalled_s=1.0) and stuck.calls >= 2
    assert stuck._flush(timeout_sec=0) is None and stuck._disconnect_orphaned_recordings() is None  # defused
    assert flushed(Stuck(after=1), f, stalled_s=1.0)
    growing = Stuck(grow=f, after=6)  # writing slowly for ~3 s: longer than stalled_s, never stalled
    assert flushed(growing, f, stalled_s=1.0) and growing.calls == 6
