"""The camera model: projection, Jacobian, OpenCV↔OpenGL pose, calibration files."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pipeline.core.calibration import load_calibration, save_calibration
from pipeline.core.camera import Camera, StereoRig, cv_to_gl_pose, project, project_jacobian
from pipeline.core.errors import CalibrationError


@pytest.fixture
def rig() -> StereoRig:
    return StereoRig.from_parameters(640, 480, (610.0, 590.0), (331.7, 236.2), baseline=0.25, toe_in_deg=4.0)


def test_projection_matches_opencv(rig):
    rng = np.random.default_rng(0)
    X = rng.uniform([-1, -1, 1.5], [1, 1, 6], size=(50, 3))
    for cam in rig.cameras:
        rvec, _ = cv2.Rodrigues(cam.R)
        ref, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, None)
        np.testing.assert_allclose(cam.project(X), ref.reshape(-1, 2), atol=1e-9)


def test_jacobian_matches_finite_differences(rig):
    rng = np.random.default_rng(1)
    X = rng.uniform([-1, -1, 1.5], [1, 1, 6], size=(20, 3))
    J = rig.jacobian(X)
    eps = 1e-6
    for j in range(3):
        d = np.zeros(3)
        d[j] = eps
        num = (rig.project(X + d) - rig.project(X - d)) / (2 * eps)
        np.testing.assert_allclose(J[:, :, j], num, rtol=1e-6, atol=1e-6)


def test_toe_in_right_camera_turns_towards_left_axis(rig):
    # a point on the left optical axis far away projects right of the right camera's centre column
    # when the rig converges, i.e. the right camera looks towards the left camera's axis.
    X = np.array([[0.0, 0.0, rig.baseline / np.tan(np.radians(4.0))]])
    u = rig.right.project(X)[0, 0]
    assert abs(u - rig.right.K[0, 2]) < 1e-6
    assert np.allclose(rig.right.center, [0.25, 0, 0])


def test_cv_to_gl_pose_maps_axes():
    rng = np.random.default_rng(2)
    R, _ = cv2.Rodrigues(rng.normal(size=3))
    t = rng.normal(size=3)
    pose = cv_to_gl_pose(R, t)  # camera → world in OpenGL axes
    X = rng.normal(size=3)
    x_cv = R @ X + t
    x_gl = np.linalg.inv(pose) @ np.append(X, 1.0)
    np.testing.assert_allclose(x_gl[:3], [x_cv[0], -x_cv[1], -x_cv[2]], atol=1e-12)


def test_normalize_and_projection_agree(rig):
    X = np.array([[0.3, -0.2, 3.0]])
    n = rig.normalized().project(X)
    np.testing.assert_allclose(rig.normalize(rig.project(X)), n, atol=1e-12)


def test_calibration_round_trip(tmp_path, rig):
    save_calibration(rig, tmp_path / "calib.yaml")
    back = load_calibration(tmp_path)  # folder holding calib.yaml
    for a, b in zip(rig.cameras, back.cameras, strict=True):
        np.testing.assert_allclose(a.P, b.P, atol=1e-12)
    assert back.image_size == (640, 480)
    fs = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_READ)
    np.testing.assert_allclose(fs.getNode("P2").mat(), rig.right.P, atol=1e-12)


def _synthetic_stereo_calibration():
    """Run cv2.stereoCalibrate on exact chessboard views of a known rig."""
    rig = StereoRig.from_parameters(640, 480, 600.0, (320.0, 240.0), baseline=0.2, toe_in_deg=2.0)
    obj = np.array([[x * 0.04, y * 0.04, 0.0] for y in range(6) for x in range(9)], np.float32)
    rng = np.random.default_rng(3)
    objs, img1, img2 = [], [], []
    for _ in range(8):
        R, _ = cv2.Rodrigues(rng.normal(scale=0.3, size=3))
        X = obj @ R.T + np.array([-0.15, -0.1, 1.2 + rng.uniform(0, 0.5)])
        objs.append(obj)
        img1.append(rig.left.project(X).astype(np.float32))
        img2.append(rig.right.project(X).astype(np.float32))
    K = rig.left.K.copy()
    flags = cv2.CALIB_FIX_INTRINSIC
    ret = cv2.stereoCalibrate(objs, img1, img2, K, np.zeros(5), K.copy(), np.zeros(5), (640, 480), flags=flags)
    return rig, ret


def test_file_written_by_opencv_stereo_calibrate_loads(tmp_path):
    rig, (_, K1, D1, K2, D2, R, T, _E, _F) = _synthetic_stereo_calibration()
    fs = cv2.FileStorage(str(tmp_path / "calib.yaml"), cv2.FILE_STORAGE_WRITE)
    fs.write("image_width", 640)
    fs.write("image_height", 480)
    for k, v in dict(K1=K1, D1=D1, K2=K2, D2=D2, R=R, T=T).items():
        fs.write(k, v)
    fs.release()
    back = load_calibration(tmp_path / "calib.yaml")
    np.testing.assert_allclose(back.R, rig.R, atol=1e-6)
    np.testing.assert_allclose(back.T, rig.T, atol=1e-6)


@pytest.mark.parametrize("ncoef", [5, 8, 12, 14])
def test_opencv_stereo_calib_sample_layout_loads(tmp_path, ncoef):
    D = np.zeros((1, ncoef))
    D[0, :2] = [-0.2, 0.05]
    K = np.array([[600.0, 0, 320], [0, 600, 240], [0, 0, 1]])
    fs = cv2.FileStorage(str(tmp_path / "intrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in dict(M1=K, D1=D, M2=K, D2=D).items():
        fs.write(k, v)
    fs.release()
    R, T = np.eye(3), np.array([[-0.3], [0.0], [0.0]])
    fs = cv2.FileStorage(str(tmp_path / "extrinsics.yml"), cv2.FILE_STORAGE_WRITE)
    for k, v in dict(R=R, T=T, R1=R, R2=R, P1=np.zeros((3, 4)), P2=np.zeros((3, 4)), Q=np.eye(4)).items():
        fs.write(k, v)
    fs.release()
    rig = load_calibration(tmp_path)
    assert rig.left.D.size == ncoef
    # undistortion inverts OpenCV's own distortion
    X = np.array([[0.2, 0.15, 1.0]])
    dist, _ = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, D)
    np.testing.assert_allclose(rig.left.undistort(dist.reshape(-1, 2)), rig.left.project(X), atol=1e-3)


def test_opencv4_yaml_header_loads(tmp_path, rig):
    save_calibration(rig, tmp_path / "calib.yaml")
    text = (tmp_path / "calib.yaml").read_text().replace("%YAML 1.2", "%YAML:1.0")
    (tmp_path / "calib.yaml").write_text(text)
    assert load_calibration(tmp_path / "calib.yaml").image_size == (640, 480)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("%YAML:1.0\n---\nK1: [1, 2\n  ::", "not a readable"),
        ("%YAML:1.0\n---\nimage_width: 640\n", "missing key 'K1'"),
        (
            "%YAML:1.0\n---\nK1: !!opencv-matrix\n   rows: 2\n   cols: 2\n   dt: d\n   data: [1., 0., 0., 1.]\n",
            "shape",
        ),
    ],
)
def test_malformed_calibration_is_a_clear_error(tmp_path, content, message):
    path = tmp_path / "calib.yaml"
    path.write_text(content)
    with pytest.raises(CalibrationError, match=message) as info:
        load_calibration(path)
    assert str(path) in str(info.value)


def test_missing_calibration_and_zero_baseline(tmp_path):
    with pytest.raises(CalibrationError, match="not found"):
        load_calibration(tmp_path / "nope.yaml")
    with pytest.raises(CalibrationError, match=r"no calib\.yaml"):
        load_calibration(tmp_path)
    K = np.diag([500.0, 500.0, 1.0])
    same = StereoRig(Camera(K), Camera(K), (640, 480))
    save_calibration(same, tmp_path / "calib.yaml")
    with pytest.raises(CalibrationError, match="zero baseline"):
        load_calibration(tmp_path / "calib.yaml")


def test_project_functions_are_the_camera_methods(rig):
    X = np.array([[0.1, 0.2, 2.0]])
    np.testing.assert_allclose(project(rig.right.P, X), rig.right.project(X))
    np.testing.assert_allclose(project_jacobian(rig.left.P, X), rig.left.jacobian(X))


def test_a_remembered_triangulation_is_the_batch_s_bit_for_bit(rig):
    """#42: a rig remembers single observations' triangulations (every method of a run triangulates
    the same detections): each equals the batch DLT's to the bit, and a caller changing what it got
    changes nothing remembered; a pickled rig carries none of them."""
    import pickle

    rig = StereoRig(rig.left, rig.right, rig.image_size)  # a rig of its own: nothing remembered yet
    rng = np.random.default_rng(0)
    X = rng.uniform([-0.5, -0.3, 1.5], [0.5, 0.3, 4.0], (50, 3))
    Y = rig.project(X) + rng.normal(0, 1, (50, 4))
    Y[7, 2:] = np.nan
    batch = rig.triangulate(Y)
    for _ in range(2):  # the second pass reads what the first remembered
        for k in range(len(Y)):
            one = rig.triangulate(Y[k])
            np.testing.assert_array_equal(one, batch[k])
            np.testing.assert_array_equal(rig.triangulate(Y[k][None])[0], batch[k])
            one[:] = 0.0
    assert len(rig._points) == 50
    assert len(pickle.loads(pickle.dumps(rig))._points) == 0
