"""The pixel-noise estimate a user's run makes (no σ handed in), and the gates it arms.

Held out: the rigs (second camera right, left, above), motions (smooth sinusoids, a manoeuvring
marker with white acceleration of about 8 m/s²) and seeds below were not used to choose the
estimator; 1 px detection noise, 30 fps, one camera's gross outliers (15–120 px)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from pipeline.core.calibration import save_calibration
from pipeline.core.camera import Camera, StereoRig
from pipeline.core.io import write_csv, write_text
from pipeline.core.rig import ring_rig
from pipeline.core.settings import RunSettings
from pipeline.estimate import estimate_clip
from pipeline.evaluation.noise import estimate_pixel_sigma

BASE = StereoRig.from_parameters(640, 480, 600.0, baseline=0.3)
LAYOUTS = {"right": BASE,
           "left": StereoRig(Camera(BASE.left.K), Camera(BASE.left.K, np.eye(3), np.array([0.3, 0.0, 0.0])), (640, 480)),
           "above": StereoRig(Camera(BASE.left.K), Camera(BASE.left.K, np.eye(3), np.array([0.0, 0.3, 0.0])), (640, 480))}
GATED = ("kf3d", "kf3d_rts", "ekf", "ekf_rts", "ukf", "spsa_stereo")


def _motion(kind: str, n: int, seed: int) -> np.ndarray:
    t = np.arange(n) / 30
    rng = np.random.default_rng(seed)
    if kind == "smooth":
        f, ph = rng.uniform(0.2, 0.6, 3), rng.uniform(0, 6, 3)
        return np.c_[0.3 * np.sin(2 * np.pi * f[0] * t + ph[0]), 0.15 * np.sin(2 * np.pi * f[1] * t + ph[1]),
                     2.2 + 0.4 * np.sin(2 * np.pi * f[2] * t + ph[2])]
    v = np.cumsum(rng.normal(0, 8, (n, 3)), axis=0) / 30
    X = np.cumsum(v - v.mean(axis=0), axis=0) / 30
    X -= X.mean(axis=0)
    return X / np.abs(X).max() * [0.35, 0.2, 0.4] + [0.0, 0.0, 2.2]


def _observe(rig, X: np.ndarray, seed: int, frac: float) -> np.ndarray:
    rng = np.random.default_rng(seed + 1000)
    Y = rig.project(X) + rng.normal(0, 1.0, (len(X), 2 * rig.n))
    bad = rng.random(len(X)) < frac
    Y[bad, 2:4] += rng.uniform(15, 120, (bad.sum(), 2)) * rng.choice([-1, 1], (bad.sum(), 2))
    return Y


def _clip(folder, rig: StereoRig, X: np.ndarray, Y: np.ndarray):
    """A clip a user could hand `estimate`: calibration, frame rate, detections, truth; no footage."""
    folder.mkdir(parents=True)
    save_calibration(rig, folder / "calib.yaml", units="m")
    write_text(folder / "clip.yaml", "fps: 30\n")
    rows = [(k, cam, "m", y[2 * c], y[2 * c + 1], 50, 1.0) for k, y in enumerate(Y)
            for c, cam in enumerate(("left", "right")) if np.all(np.isfinite(y[2 * c : 2 * c + 2]))]
    write_csv(folder / "out" / "detections.csv", ["frame", "camera", "marker", "u", "v", "area", "score"], rows)
    write_csv(folder / "truth.csv", ["frame", "marker", "x", "y", "z"], [(k, "m", *x) for k, x in enumerate(X)])
    return folder


@pytest.mark.parametrize("frac", [0.0, 0.05, 0.1, 0.2])
@pytest.mark.parametrize("rig", [LAYOUTS["right"], LAYOUTS["above"], ring_rig(4).in_frame_of(0)], ids=["right", "above",
                                                                                                       "ring4"])
def test_the_noise_estimate_ignores_one_camera_s_outliers(rig, frac):
    """1 px noise, and up to a fifth of the frames with one camera's detection 15–120 px off: the
    estimate stays within 0.85–1.2 px (the trimmed mean it replaces gave 4 px at 5 %, 22 px at 20 %)."""
    sigmas = []
    for seed in range(3):
        X = _motion("smooth", 300, seed)
        sigmas.append(estimate_pixel_sigma(rig, {"m": _observe(rig, X, seed, frac)}))
    assert 0.85 < float(np.median(sigmas)) < (1.2 if frac < 0.2 else 1.45), sigmas


@pytest.mark.slow
def test_estimate_as_a_user_runs_it_holds_with_outliers(tmp_path):
    """Acceptance (issue "Sure-footed estimation"): `estimate` with σ estimated, on the held-out
    layouts and motions, one camera with 5 % and 10 % gross outliers: every gated method within
    1.3× (5 %) and 2× (10 %) of its clean RMSE, median over the clips, and none diverges (5×)."""
    ratios: dict[tuple[float, str], list[float]] = {}
    for name, rig in LAYOUTS.items():
        for kind in ("smooth", "manoeuvring"):
            X = _motion(kind, 300, 7)
            runs = {}
            for frac in (0.0, 0.05, 0.1):
                clip = _clip(tmp_path / f"{name}_{kind}_{frac}", rig, X, _observe(rig, X, 7, frac))
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    res = estimate_clip(clip, RunSettings(methods=GATED, time_offset="off"))
                runs[frac] = {m: res.metrics["methods"][m]["rmse"] for m in GATED}
            for frac in (0.05, 0.1):
                for m in GATED:
                    ratios.setdefault((frac, m), []).append(runs[frac][m] / runs[0.0][m])
    for (frac, m), r in ratios.items():
        assert np.median(r) <= (1.3 if frac == 0.05 else 2.0), (frac, m, r)
        assert max(r) < 5.0, (frac, m, r)
