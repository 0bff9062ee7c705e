"""The renderer against the camera model: rendered centroids match P·X from the clip's calib.yaml."""

from __future__ import annotations

import os
import subprocess
import sys

import cv2
import numpy as np

from pipeline.core.calibration import load_calibration
from pipeline.core.clip import TARGET_TRUTH_COLUMNS, TRUTH_COLUMNS, TRUTH_EXTRA_COLUMNS
from pipeline.core.io import read_csv

HUE = {"red": 0, "green": 1, "blue": 2}


def _centroid(img_rgb: np.ndarray, u: float, v: float, channel: int, r: int) -> tuple[float, float]:
    """Intensity-weighted centroid of the marker's colour excess in a window around (u, v)."""
    x0, y0 = round(u), round(v)
    patch = img_rgb[y0 - r : y0 + r + 1, x0 - r : x0 + r + 1].astype(float)
    others = [c for c in range(3) if c != channel]
    w = np.clip(patch[..., channel] - patch[..., others].max(-1) - 40, 0, None)
    ys, xs = np.mgrid[-r : r + 1, -r : r + 1]
    return float((w * xs).sum() / w.sum() + x0), float((w * ys).sum() / w.sum() + y0)


def test_rendered_centroids_match_projection(png_clip):
    """Catches the OpenGL/OpenCV traps (axes, the half pixel): median ≤ 0.15 px, max ≤ 0.5 px."""
    rig = load_calibration(png_clip / "calib.yaml")  # the calibration the clip carries
    assert rig.left.K[0, 2] != (rig.image_size[0] - 1) / 2  # off-centre principal point
    assert not np.allclose(rig.R, np.eye(3))  # toe-in
    tr = read_csv(png_clip / "truth.csv")
    errors = []
    for k in range(int(tr["frame"].max()) + 1):
        for c, cam in enumerate(("left", "right")):
            img = cv2.imread(str(png_clip / cam / f"{k:06d}.png"))[..., ::-1]
            X = {}
            for name, ch in HUE.items():
                sel = (tr["frame"] == k) & (tr["marker"] == name)
                if not tr[f"visible_{cam}"][sel][0]:
                    continue
                X[name] = np.array([tr["x"][sel][0], tr["y"][sel][0], tr["z"][sel][0]])
                uv = rig.cameras[c].project(X[name][None])[0]  # P·X from calib.yaml, not truth's columns
                np.testing.assert_allclose(uv, [tr[f"u_{cam}"][sel][0], tr[f"v_{cam}"][sel][0]], atol=1e-6)
                r_px = rig.cameras[c].K[0, 0] * 0.05 / rig.cameras[c].depth(X[name][None])[0]
                w = int(np.ceil(r_px + 4))
                if not rig.in_image(uv[None], margin=w)[0]:
                    continue  # not fully in frame
                cu, cv_ = _centroid(img, uv[0], uv[1], ch, w)
                errors.append(np.hypot(cu - uv[0], cv_ - uv[1]))
    errors = np.array(errors)
    assert len(errors) > 100
    assert np.median(errors) <= 0.15, np.median(errors)
    assert errors.max() <= 0.5, errors.max()


def test_clip_contents_and_truth_schema(png_clip, target_clip):
    for clip, frames in ((png_clip, 24), (target_clip, 40)):
        for cam in ("left", "right"):
            assert len(list((clip / cam).glob("*.png"))) == frames
        assert (clip / "scenario.yaml").is_file() and (clip / "calib.yaml").is_file()
        header = (clip / "truth.csv").read_text().splitlines()[0].split(",")
        assert header == TRUTH_COLUMNS + TRUTH_EXTRA_COLUMNS
        assert not list(clip.glob(".*partial*"))
    tt = read_csv(target_clip / "target_truth.csv", TARGET_TRUTH_COLUMNS)
    assert len(tt["frame"]) == 40 and np.all(np.isfinite(tt["alpha"]))


def test_mp4_clip_has_all_frames(mp4_clip):
    for cam in ("left", "right"):
        cap = cv2.VideoCapture(str(mp4_clip / f"{cam}.mp4"))
        n = 0
        while cap.read()[0]:
            n += 1
        assert n == 24


def test_render_is_deterministic(png_clip, tmp_path):
    from renderers.render import render_clip
    from renderers.scenario import parse_scenario
    from tests.conftest import small_multi_marker

    render_clip(parse_scenario(small_multi_marker(frames=3)), tmp_path, fmt="png", workers=1)
    for cam in ("left", "right"):
        a = cv2.imread(str(tmp_path / cam / "000002.png"))
        b = cv2.imread(str(png_clip / cam / "000002.png"))
        assert np.array_equal(a, b)
    assert (tmp_path / "truth.csv").read_text().splitlines()[1:10] == (png_clip / "truth.csv").read_text().splitlines()[1:10]


def test_no_gl_backend_is_one_clear_line(tmp_path):
    """A scene only pyrender draws (lit shading) without EGL: one line saying how to get it."""
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl", "__EGL_VENDOR_LIBRARY_FILENAMES": str(tmp_path / "none.json")}
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline.app.cli", "render", "skin_wall", "-o", str(tmp_path / "c"), "--frames", "2"],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    err = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert len(err) == 1 and "OpenGL backend" in err[0] and "EGL" in err[0] and "OSMesa" in err[0]
    assert not (tmp_path / "c" / "left.mp4").exists()


def test_colour_only_readback_is_pyrenders_image_and_multisample_is_a_setting():
    """The renderer reads back only the colour image: the same pixels as pyrender's own read-back
    (which also reads depth); ``multisample: 0`` renders without anti-aliasing (hard edges)."""
    import numpy as np

    from renderers.motion import simulate_truth
    from renderers.scenario import load_scenario
    from renderers.scene import StereoScene, create_offscreen_renderer, set_multisample

    scen = load_scenario("default").with_overrides(frames=3)
    rig = scen.rig.build()
    scene = StereoScene(scen, rig, simulate_truth(scen))
    r = create_offscreen_renderer(*rig.image_size)
    try:
        scene.set_frame(1)
        ours = scene.render(r, 0).copy()
        inner = r._renderer
        inner._read_main_framebuffer = type(inner)._read_main_framebuffer.__get__(inner)  # pyrender's own
        np.testing.assert_array_equal(scene.render(r, 0), ours)
        set_multisample(r, 0)
        hard = scene.render(r, 0)
        assert 0 < int((np.abs(hard.astype(int) - ours.astype(int)).max(axis=2) > 8).sum()) < 0.02 * hard[..., 0].size
    finally:
        set_multisample(r, 4)
        r.delete()
