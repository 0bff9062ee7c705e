"""Shared fixtures: small rendered clips (rendered once per session) and the shared-data paths.

Tests render with ``workers=1``, in their own process: a pool's two fresh interpreters cost about
2 s of CPU per clip, and the pool itself is exercised by the tests that run the CLI."""

from __future__ import annotations

import os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # before numpy loads: tiny
    os.environ.setdefault(_var, "1")  # matrices, where BLAS threads cost 2–15× on a loaded machine
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from pipeline.core.settings import RunSettings  # noqa: E402
from renderers.render import render_clip  # noqa: E402
from renderers.scenario import load_scenario, parse_scenario  # noqa: E402

REPO = Path(__file__).resolve().parent.parent
SHARED = REPO.parent / "shared"
REALDATA = SHARED / "realdata"
BALL = REALDATA / "ball2.mp4"
needs_ball = pytest.mark.skipif(not BALL.is_file(), reason=f"real footage {BALL} not present (shared/realdata)")


def small_multi_marker(frames: int = 24, width: int = 320, height: int = 240, **render) -> dict:
    """A toe-in rig with an off-centre principal point, three markers and a distractor."""
    return {
        "name": "small_multi",
        "frames": frames,
        "fps": 30,
        "seed": 3,
        "rig": {"width": width, "height": height, "focal": 300.0, "principal_point": [166.3, 113.8],
                "baseline": 0.3, "toe_in_deg": 3.0},
        "render": {"shading": "flat", "noise_std": 2.0, "blur_sigma": 0.6, **render},
        "objects": [
            {"name": "red", "color": [230, 30, 30], "radius": 0.05,
             "motion": {"type": "constant_velocity", "start": [-0.3, -0.1, 1.6], "velocity": [0.3, 0.1, 0.9]}},
            {"name": "green", "color": [30, 200, 40], "radius": 0.05,
             "motion": {"type": "sinusoid", "center": [0.25, 0.15, 2.2], "amplitude": [0.3, 0.1, 0.3],
                        "frequency_hz": 0.8}},
            {"name": "blue", "color": [40, 60, 230], "radius": 0.05,
             "motion": {"type": "constant_acceleration", "start": [0.0, -0.35, 2.5], "velocity": [-0.2, 0.0, 0.0],
                        "acceleration": [0.5, 0.2, 0.0]}},
        ],
        "distractors": [{"shape": "cube", "color": [200, 40, 200], "size": 0.12, "position": [0.5, -0.3, 3.0]}],
    }


@pytest.fixture(scope="session")
def png_clip(tmp_path_factory) -> Path:
    """A lossless 320×240 clip of three markers (rendered once per test session)."""
    out = tmp_path_factory.mktemp("clips") / "multi_png"
    render_clip(parse_scenario(small_multi_marker()), out, fmt="png", workers=1)
    return out


@pytest.fixture(scope="session")
def mp4_clip(tmp_path_factory) -> Path:
    """The same scene as MP4 videos."""
    out = tmp_path_factory.mktemp("clips") / "multi_mp4"
    render_clip(parse_scenario(small_multi_marker()), out, fmt="mp4", workers=1)
    return out


def target_scenario(rasteriser: str = "pyrender"):
    """40 frames of the four-point target, drawn by ``rasteriser``."""
    scen = load_scenario("four_point").with_overrides(frames=40)
    data = scen.model_dump(mode="json")
    data["render"]["rasteriser"] = rasteriser
    return type(scen).model_validate(data)


@pytest.fixture(scope="session")
def target_clip(tmp_path_factory) -> Path:
    """A short four-point-target clip (PNG), drawn by pyrender, the reference rasteriser, as when
    the tests that use it were written (on the analytic render of it kalman_bucy's clean α error
    is half as large: tests/estimators/test_survive.py)."""
    out = tmp_path_factory.mktemp("clips") / "target"
    render_clip(target_scenario(), out, fmt="png", workers=1)
    return out


@pytest.fixture(scope="session")
def target_clip_analytic(tmp_path_factory) -> Path:
    """The same clip drawn by the analytic rasteriser (the default for it)."""
    out = tmp_path_factory.mktemp("clips") / "target_analytic"
    render_clip(target_scenario("analytic"), out, fmt="png", workers=1)
    return out


@pytest.fixture(scope="module")
def detected_clip(tmp_path_factory) -> Path:
    """The sample clip as a real rig ships it (videos + calib.yaml), detected and estimated: the
    starting point of the bad-input tables (each case copies it)."""
    from detectors.stage import detect_clip
    from pipeline.estimate import estimate_clip
    from tests.helpers import RED, real_copy

    clip = real_copy(tmp_path_factory.mktemp("bad") / "clip")
    detect_clip(clip, RunSettings(detector="blob", markers=[RED]))
    estimate_clip(clip, RunSettings(methods=["triangulation"]))
    return clip


@pytest.fixture(scope="session")
def ball_reference() -> dict[int, tuple[float, float]]:
    """ball2.mp4's ball centre per left frame from a strict HSV range (confident frames only): the
    reference that the detectors and learned marker ranges are measured against."""
    from detectors.blob import BlobDetector, MarkerColor
    from pipeline.core.frames import StereoFrameSource

    strict = BlobDetector([MarkerColor.parse("ball:35-55:70:60")], min_area=800)
    ref = {}
    for fr in StereoFrameSource(BALL):
        d = strict.detect(fr.left)
        if d and d[0].score > 0.55:
            ref[fr.index] = (d[0].u, d[0].v)
    return ref


@pytest.fixture(scope="module")
def receding():
    """The ``receding`` scenario's truth over 300 frames: (rig, dt, positions, velocities)."""
    from renderers.motion import simulate_truth
    from renderers.scenario import load_scenario

    s = load_scenario("receding").with_overrides(frames=300)
    tr = simulate_truth(s)
    return s.rig.build(), s.dt, tr.positions[:, 0], tr.velocities[:, 0]
