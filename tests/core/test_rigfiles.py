"""N-camera rigs and their files: every format round-trips exactly, Qualisys and Anipose files are
read as their tools mean them, bad files are one clear error."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from pipeline.core.camera import Camera, StereoRig
from pipeline.core.errors import CalibrationError
from pipeline.core.rig import Rig, look_at, ring_rig
from pipeline.core.rigfiles import find_rig, load_rig, save_rig


def _lab_rig() -> Rig:
    """Four cameras of a real mocap rig's magnitude: 1920×1080, f ≈ 1400–1700 px, 3–4 m from the
    volume, in a lab frame (not a camera's), each with its own distortion (k3 too) and offset."""
    rng = np.random.default_rng(7)
    cams, names, sizes = [], [], []
    for k, a in enumerate(np.deg2rad([20, 110, 200, 290])):
        centre = np.array([3.2 * np.cos(a), 3.4 * np.sin(a), 2.1 + 0.1 * k])
        R, t = look_at(centre, np.array([0.1, -0.2, 0.9]), up=np.array([0.0, 0.0, 1.0]))
        K = np.array([[1400 + 90 * k, 0.7, 950.3 + k], [0.0, 1401.5 + 90 * k, 541.2 - k], [0, 0, 1]])
        D = np.array([-0.21, 0.07, 3e-4, -2e-4, -0.013]) * (1 + 0.1 * rng.standard_normal(5))
        cams.append(Camera(K, R, t, D))
        names.append(f"Miqus_{k + 1}")
        sizes.append((1920, 1080))
    return Rig(tuple(cams), tuple(names), tuple(sizes), (0.0, 0.0021, -0.0013, 0.004))


def _max_difference(a: Rig, b: Rig) -> float:
    assert a.names == b.names and a.sizes == b.sizes and a.n == b.n
    return max(float(np.max(np.abs(np.ravel(getattr(x, f)) - np.ravel(getattr(y, f)))))
               for x, y in zip(a.cameras, b.cameras, strict=True) for f in "KRtD")


@pytest.mark.parametrize("name", ["calib.toml", "rig.json", "rig.yaml", "rig.xml", "cameras", "lab.qca.txt"])
@pytest.mark.parametrize("units", [None, "mm"])
def test_every_format_round_trips_exactly(tmp_path, name, units):
    rig = _lab_rig()
    save_rig(rig, tmp_path / name, units)
    back = load_rig(tmp_path / name)
    assert _max_difference(rig, back) < 1e-12
    if not name.endswith(".qca.txt"):  # Qualisys rigs are hardware-synchronised: no offsets in the file
        assert back.offsets == rig.offsets


def test_two_camera_calib_yaml_is_a_rig_of_two(tmp_path):
    stereo = StereoRig.from_parameters(640, 480, 600.0, baseline=0.3, toe_in_deg=3.0)
    save_rig(Rig.from_stereo(stereo), tmp_path / "calib.yaml")
    back = load_rig(tmp_path)
    assert back.names == ("left", "right") and _max_difference(Rig.from_stereo(stereo), back) < 1e-12
    pair = back.stereo(0, 1)
    assert isinstance(pair, StereoRig) and abs(pair.baseline - 0.3) < 1e-12


def test_qualisys_file_is_read_as_pose2sim_reads_it(tmp_path):
    """A hand-written .qca.txt: camera at (1000, −2000, 1500) mm whose optical axis (its −z, as
    Qualisys axes point backwards) looks along world +y; intrinsics in 1/64 px."""
    text = """<?xml version="1.0"?>
<calibration source="test" type="regular"><cameras>
 <camera active="1" serial="A" model="Miqus M3" viewrotation="0" avg-residual="0.3">
  <fov_video left="0" top="0" right="1823" bottom="1087"/>
  <transform x="1000" y="-2000" z="1500" r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0"/>
  <intrinsic focallength="8" focalLengthU="89600" focalLengthV="89664" centerPointU="58368" centerPointV="34816"
   skew="0" radialDistortion1="-12.8" radialDistortion2="6.4" radialDistortion3="0.64"
   tangentalDistortion1="0.0128" tangentalDistortion2="-0.0064"/>
 </camera>
 <camera active="1" serial="B" model="Miqus M3" viewrotation="0" avg-residual="0.3">
  <fov_video left="0" top="0" right="1823" bottom="1087"/>
  <transform x="-1000" y="-2000" z="1500" r11="1" r12="0" r13="0" r21="0" r22="0" r23="1" r31="0" r32="-1" r33="0"/>
  <intrinsic focalLengthU="89600" focalLengthV="89600" centerPointU="58368" centerPointV="34816" skew="0"
   radialDistortion1="0" radialDistortion2="0" radialDistortion3="0" tangentalDistortion1="0" tangentalDistortion2="0"/>
 </camera></cameras></calibration>"""
    path = tmp_path / "lab.qca.txt"
    path.write_text(text)
    rig = load_rig(path)
    a = rig.cameras[0]
    assert rig.names == ("A", "B") and rig.sizes == ((1824, 1088), (1824, 1088))
    np.testing.assert_allclose(a.K, [[1400, 0, 912], [0, 1401, 544], [0, 0, 1]])
    np.testing.assert_allclose(a.D, [-0.2, 0.1, 0.0002, -0.0001, 0.01])  # k3 kept, last
    np.testing.assert_allclose(a.center, [1.0, -2.0, 1.5], atol=1e-12)  # millimetres → metres
    np.testing.assert_allclose(a.R[2], [0.0, 1.0, 0.0], atol=1e-12)  # the optical axis: world +y
    ahead = np.array([[1.0, 1.0, 1.5]])  # 3 m in front, on the axis: the principal point
    np.testing.assert_allclose(a.project(ahead), [[912.0, 544.0]], atol=1e-9)
    above = np.array([[1.0, 1.0, 2.0]])  # world +z is up: above the axis appears higher (smaller v)
    assert a.project(above)[0, 1] < 544.0


def test_anipose_toml_as_anipose_writes_it(tmp_path):
    """aniposelib's ``CameraGroup.dump`` layout (floats everywhere, trailing commas, metadata)."""
    (tmp_path / "calib.toml").write_text("""[cam_0]
name = "A"
size = [ 1280.0, 1024.0,]
matrix = [ [ 1500.0, 0.0, 639.5,], [ 0.0, 1500.0, 511.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.1, 0.02, 0.0, 0.0, 0.004,]
rotation = [ 0.0, 0.0, 0.0,]
translation = [ 0.0, 0.0, 0.0,]

[cam_1]
name = "B"
size = [ 1280.0, 1024.0,]
matrix = [ [ 1500.0, 0.0, 639.5,], [ 0.0, 1500.0, 511.5,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.1, 0.02, 0.0, 0.0, 0.004,]
rotation = [ 0.0, -0.3, 0.0,]
translation = [ -300.0, 0.0, 20.0,]

[metadata]
adjusted = false
error = 0.0
""")
    with pytest.warns(UserWarning, match="millimetres"):  # 300 apart, no unit: almost surely mm
        load_rig(tmp_path / "calib.toml")
    rig = load_rig(tmp_path / "calib.toml", units="mm")
    assert rig.names == ("A", "B") and rig.sizes == ((1280, 1024), (1280, 1024))
    assert rig.cameras[1].D[4] == 0.004  # k3 kept
    np.testing.assert_allclose(rig.cameras[1].R, cv2.Rodrigues(np.array([0.0, -0.3, 0.0]))[0])
    np.testing.assert_allclose(rig.cameras[1].t, [-0.3, 0.0, 0.02])


def test_truth_pixels_of_a_qualisys_rig_equal_opencv(tmp_path):
    """Acceptance: a 4-camera rig read from a .qca.txt projects as cv2.projectPoints, 1e-6 px."""
    save_rig(_lab_rig(), tmp_path / "lab.qca.txt")
    rig = load_rig(tmp_path / "lab.qca.txt")
    X = np.random.default_rng(3).uniform([-0.8, -0.8, 0.2], [0.8, 0.6, 1.8], (40, 3))
    for cam in rig.cameras:
        ref = cv2.projectPoints(X, cv2.Rodrigues(cam.R)[0], cam.t, cam.K, cam.D)[0].reshape(-1, 2)
        np.testing.assert_allclose(cam.project_distorted(X), ref, atol=1e-6)
        assert np.all(cam.depth(X) > 0)


def test_in_frame_of_the_first_camera_keeps_every_projection():
    rig = _lab_rig()
    first = rig.in_frame_of(0)
    np.testing.assert_allclose(first.cameras[0].R, np.eye(3), atol=1e-12)
    X = np.random.default_rng(4).uniform([-0.5, -0.5, 0.5], [0.5, 0.5, 1.5], (10, 3))
    c0 = rig.cameras[0]
    X0 = X @ c0.R.T + c0.t
    np.testing.assert_allclose(first.project(X0), rig.project(X), atol=1e-9)


def test_find_rig_in_a_clip_folder(tmp_path):
    assert find_rig(tmp_path) is None
    save_rig(ring_rig(3), tmp_path / "session.qca.txt")
    assert find_rig(tmp_path) == tmp_path / "session.qca.txt"
    assert load_rig(tmp_path).n == 3


@pytest.mark.parametrize(("name", "text", "problem"), [
    ("calib.toml", "[cam_0]\nname='a'\n", "lacks matrix"),
    ("calib.toml", "[metadata]\nadjusted=false\n", "no [cam_N] tables"),
    ("calib.toml", "[cam_0]\nfisheye=true\n", "fisheye"),
    ("rig.json", '{"cameras": [{"K": [1, 2], "R": [], "t": [], "size": [1, 1]}]}', "has 2 values, expected 9"),
    ("rig.json", "[1, 2]", "not a JSON rig"),
    ("x.qca.txt", "<calibration><cameras/></calibration>", "no <cameras><camera>"),
    ("x.qca.txt", "<calibration", "not a readable Qualisys"),
    ("rig.yaml", "%YAML:1.0\nfoo: 1\n", "needs nb_cameras"),
    ("rig.cfg", "", "unknown rig format"),
])
def test_bad_rig_files_are_one_clear_error(tmp_path, name, text, problem):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(CalibrationError, match=problem.replace("[", r"\[").replace("(", r"\(")) as err:
        load_rig(path)
    assert str(path) in str(err.value)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.binary(max_size=300), name=st.sampled_from(["calib.toml", "rig.json", "a.qca.txt", "rig.yaml"]))
def test_fuzzed_rig_files_never_crash(tmp_path, data, name):
    path = tmp_path / name
    path.write_bytes(data)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            load_rig(path)
        except CalibrationError as exc:
            assert "\n" not in str(exc)


def test_rig_convert_command(tmp_path):
    from pipeline.app.cli import app

    save_rig(_lab_rig(), tmp_path / "lab.qca.txt")
    run = CliRunner().invoke
    res = run(app, ["rig", "convert", str(tmp_path / "lab.qca.txt"), str(tmp_path / "calib.toml")])
    assert res.exit_code == 0, res.output
    assert _max_difference(load_rig(tmp_path / "lab.qca.txt"), load_rig(tmp_path / "calib.toml")) < 1e-12
    before = (tmp_path / "calib.toml").read_bytes()
    res = run(app, ["rig", "convert", str(tmp_path / "lab.qca.txt"), str(tmp_path / "calib.toml")])
    assert res.exit_code != 0 and (tmp_path / "calib.toml").read_bytes() == before  # never replaced
    res = run(app, ["rig", "show", str(tmp_path / "calib.toml")])
    assert res.exit_code == 0 and "Miqus_4" in res.output


