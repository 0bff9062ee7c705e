"""The analytic rasteriser against independent references: a solid's covered area and centre
against its projection in closed form, rendered clips against pyrender's (the reference rasteriser)
and the truth, and the scenes it refuses."""

from __future__ import annotations

import numpy as np
import pytest

from renderers.motion import simulate_truth
from renderers.scenario import load_scenario, parse_scenario
from tests.conftest import small_multi_marker
from tests.renderers.test_render import test_rendered_centroids_match_projection as centroids_match_projection


def _one_solid(shape: str, size: float, at: tuple[float, float, float], normal=None, samples: int = 4, R=None):
    """Coverage (0..1 per pixel) of one white solid over black, 320×240, f = 300, from the analytic
    scene's own drawing call."""
    from renderers.raster import AnalyticScene

    scen = load_scenario("default").with_overrides(frames=1)
    data = scen.model_dump(mode="json")
    data["rig"].update(width=320, height=240, focal=300.0, principal_point=[161.3, 118.7], toe_in_deg=0.0)
    data["render"].update(background="plain", background_color=[0, 0, 0], multisample=4 if samples > 1 else 0)
    scene = AnalyticScene(type(scen).model_validate(data), type(scen).model_validate(data).rig.build(),
                          simulate_truth(scen))
    from renderers.scene import Shape

    scene.shapes = [Shape(shape, (size,) if shape == "sphere" else (size, 1e-6) if shape == "cylinder" else (size,) * 3,
                          (255, 255, 255))]
    scene.kinds = np.array([{"sphere": 0, "cylinder": 1, "box": 2}[shape]])
    scene.colors = np.array([[255.0, 255.0, 255.0]])
    pose = np.eye(4)
    if normal is not None:
        from renderers.scene import _frame_from_normal

        pose[:3, :3] = _frame_from_normal(np.asarray(normal, float))
    if R is not None:
        pose[:3, :3] = R
    pose[:3, 3] = at
    scene.poses = pose[None]
    return scene.render(None, 0)[..., 0] / 255.0, scene.views[0].K


def _moments(cov: np.ndarray) -> tuple[float, float, float]:
    v, u = np.mgrid[: cov.shape[0], : cov.shape[1]]
    a = cov.sum()
    return float(a), float((cov * u).sum() / a), float((cov * v).sum() / a)


@pytest.mark.parametrize("at", [(0.0, 0.0, 1.0), (0.11, -0.07, 1.3), (-0.2, 0.13, 0.9)])
def test_sphere_covers_its_projected_ellipse(at):
    """A sphere's image is the ellipse where the cone tangent to it meets the image plane: its area
    and centre in closed form (the conic's), held to 0.2 % and 0.01 px."""
    r = 0.03
    cov, K = _one_solid("sphere", r, at)
    area, cu, cv = _moments(cov)
    # the tangent cone's conic in normalised coordinates: (c·d)² = (‖c‖² − r²)‖d‖², d = (x, y, 1)
    c = np.asarray(at)
    M = np.outer(c, c) - (c @ c - r * r) * np.eye(3)
    A, b, k = M[:2, :2], M[:2, 2], M[2, 2]
    centre = -np.linalg.solve(A, b)
    kk = k - b @ np.linalg.solve(A, b)
    area_n = np.pi * abs(kk) / np.sqrt(np.linalg.det(A))  # ellipse x'Ax = −kk
    f = K[0, 0]
    assert area == pytest.approx(area_n * f * f, rel=2e-3)
    assert cu == pytest.approx(K[0, 2] + f * centre[0], abs=0.01)
    assert cv == pytest.approx(K[1, 2] + f * centre[1], abs=0.01)


def test_disc_and_box_cover_their_projections():
    """A (1 µm thin) disc facing the camera covers π (f r / z)² around its projected centre; a cube face-on,
    turned 30° about the optical axis (edges off the sample grid's rows), covers (f s / z)² (its near
    face; the sides are hidden)."""
    cov, K = _one_solid("cylinder", 0.04, (0.05, 0.02, 1.2), normal=(0.0, 0.0, -1.0))
    area, cu, cv = _moments(cov)
    f, z = K[0, 0], 1.2
    assert area == pytest.approx(np.pi * (f * 0.04 / z) ** 2, rel=3e-3)
    assert (cu, cv) == pytest.approx((K[0, 2] + f * 0.05 / z, K[1, 2] + f * 0.02 / z), abs=0.01)
    a = np.radians(30)
    cov, K = _one_solid("box", 0.08, (0.0, 0.0, 1.5), R=np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0],
                                                                   [0, 0, 1]]))
    area, cu, cv = _moments(cov)
    assert area == pytest.approx((K[0, 0] * 0.08 / (1.5 - 0.04)) ** 2, rel=3e-3)
    assert (cu, cv) == pytest.approx((K[0, 2], K[1, 2]), abs=0.01)


def test_multisample_off_samples_each_pixel_centre():
    """Without multisampling a pixel is the solid's exactly when the ray through its centre meets it."""
    cov, K = _one_solid("sphere", 0.03, (0.0, 0.0, 1.0), samples=1)
    assert set(np.unique(cov)) <= {0.0, 1.0}
    v, u = np.mgrid[: cov.shape[0], : cov.shape[1]]
    x, y = (u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1]
    hit = 1.0 - (x * x + y * y + 1) * (1 - 0.03**2) >= 0  # the ray–sphere discriminant, centre (0, 0, 1)
    assert hit.sum() > 100 and np.array_equal(cov > 0.5, hit)


def _render_both(scen, tmp_path):
    from detectors.stage import detect_clip
    from pipeline.core.io import read_csv
    from renderers.render import render_clip

    out = {}
    for ras in ("pyrender", "analytic"):
        data = scen.model_dump(mode="json")
        data["render"]["rasteriser"] = ras
        clip = tmp_path / ras
        render_clip(type(scen).model_validate(data), clip, fmt="png", workers=1)
        detect_clip(clip)
        out[ras] = (clip, read_csv(clip / "out" / "detections.csv"), read_csv(clip / "truth.csv"))
    return out


def _compare(out) -> tuple[np.ndarray, float, float]:
    """Per-detection |Δu|, |Δv| between the two renders, and each render's median distance to the
    truth's projection."""
    (pc, pd, pt), (ac, ad, _) = out["pyrender"], out["analytic"]
    for name in ("truth.csv", "timestamps.csv", "calib.yaml", "target_truth.csv"):
        if (pc / name).exists():
            assert (pc / name).read_bytes() == (ac / name).read_bytes(), name
    key = [f"{c}|{f}|{m}" for c, f, m in zip(pd["camera"], pd["frame"], pd["marker"], strict=True)]
    assert key == [f"{c}|{f}|{m}" for c, f, m in zip(ad["camera"], ad["frame"], ad["marker"], strict=True)]
    diff = np.abs(np.concatenate([pd["u"] - ad["u"], pd["v"] - ad["v"]]))
    truth = {(f, m): i for i, (f, m) in enumerate(zip(pt["frame"], pt["marker"], strict=True))}

    def to_truth(d) -> float:
        e = [np.hypot(u - pt[f"u_{c}"][truth[f, m]], v - pt[f"v_{c}"][truth[f, m]])
             for c, f, m, u, v in zip(d["camera"], d["frame"], d["marker"], d["u"], d["v"], strict=True)]
        return float(np.median(e))

    return diff, to_truth(pd), to_truth(ad)


@pytest.mark.parametrize("name", ["default", pytest.param("rig_below", marks=pytest.mark.slow),
                                  pytest.param("drops_jitter", marks=pytest.mark.slow)])
def test_analytic_clip_is_pyrenders_within_hundredths_and_nearer_the_truth(name, tmp_path):
    """The default scenario (looked at while building) and two held out (a camera below, dropped
    frames and jitter): identical truth, timestamps and calibration; the blob centres of 24 frames
    within 0.05 px of pyrender's at the 99th percentile, 0.1 px at most; and the analytic render's
    centres no farther from the truth's projection (median) than pyrender's."""
    out = _render_both(load_scenario(name).with_overrides(frames=24), tmp_path)
    diff, to_truth_p, to_truth_a = _compare(out)
    assert len(diff) >= 150
    assert np.percentile(diff, 99) <= 0.05 and diff.max() <= 0.1, (np.percentile(diff, 99), diff.max())
    assert to_truth_a <= to_truth_p, (to_truth_a, to_truth_p)


def test_analytic_centroids_match_projection(tmp_path):
    """The renderer's OpenGL/OpenCV test (median ≤ 0.15 px, max ≤ 0.5 px against P·X from the
    clip's calib.yaml) on the analytic path: the three markers without the distractor."""
    from renderers.render import render_clip

    scen = small_multi_marker()
    scen["distractors"] = []
    s = parse_scenario(scen)
    assert s.analytic()
    render_clip(s, tmp_path / "c", fmt="png", workers=2)
    centroids_match_projection(tmp_path / "c")


def test_what_draws_a_scenario():
    """auto: analytic for flat scenes without distractors, pyrender otherwise; asking for the
    analytic rasteriser where it cannot draw is a one-line validation error."""
    assert load_scenario("default").analytic()
    assert not load_scenario("skin_wall").analytic()  # lit
    assert not load_scenario("occlusion").analytic()  # distractors
    data = load_scenario("default").model_dump(mode="json")
    data["render"]["rasteriser"] = "pyrender"
    assert not type(load_scenario("default")).model_validate(data).analytic()
    data = load_scenario("skin_wall").model_dump(mode="json")
    data["render"]["rasteriser"] = "analytic"
    with pytest.raises(ValueError, match="analytic cannot draw this scenario: lit shading"):
        type(load_scenario("default")).model_validate(data)


def test_threads_and_one_thread_write_the_same_clip(tmp_path):
    """The cameras on two threads (the default) and one after the other: the same bytes, file by file."""
    from renderers.render import render_clip

    scen = load_scenario("default").with_overrides(frames=6)
    for workers in (1, 2):
        render_clip(scen, tmp_path / str(workers), fmt="png", workers=workers)
    files = sorted(p.relative_to(tmp_path / "1") for p in (tmp_path / "1").rglob("*") if p.is_file())
    assert len(files) >= 12 + 4
    for f in files:
        assert (tmp_path / "1" / f).read_bytes() == (tmp_path / "2" / f).read_bytes(), f


def test_a_camera_thread_failing_leaves_nothing(tmp_path, monkeypatch):
    """One camera's writer fails on its fifth frame: the error comes out as it was, the other camera
    stops, and neither the clip folder nor a staging folder is left."""
    import threading

    from renderers import writers
    from renderers.render import render_clip

    real = writers.FrameWriter.write
    seen = []

    def write(self, rgb, index=None):
        seen.append(threading.current_thread().name)
        if self.final.name.startswith("right") and index == 4:
            raise OSError("disk full (simulated)")
        real(self, rgb, index)

    monkeypatch.setattr(writers.FrameWriter, "write", write)
    with pytest.raises(OSError, match="disk full"):
        render_clip(load_scenario("default").with_overrides(frames=200), tmp_path / "clip", workers=2)
    assert {n.split("_")[0] for n in seen} == {"render"}  # written on the render threads
    assert list(tmp_path.iterdir()) == []
