"""`stereotrack export --format c3d` on a rendered clip: each point's residual follows the C3D
convention (−1 none, 0 computed, > 0 measured: the mean distance to the rays of the cameras that saw
it) and its camera mask names those cameras; an independent check computes the residual from the
reprojection error instead of the rays."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from detectors.stage import detect_clip
from pipeline.core.clip import Clip
from pipeline.core.io import read_csv
from pipeline.core.settings import RunSettings
from pipeline.estimate import estimate_clip
from tests.helpers import SAMPLE, cli

GONE = range(10, 15)  # frames without the left camera's detection


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    clip = tmp_path_factory.mktemp("c3d") / "clip"
    shutil.copytree(SAMPLE, clip)
    detect_clip(clip)
    path = clip / "out" / "detections.csv"
    rows = path.read_text().splitlines()
    path.write_text("\n".join(r for r in rows if not (r.split(",")[0] in {str(k) for k in GONE}
                                                      and r.split(",")[1] == "left")) + "\n")
    estimate_clip(clip, RunSettings(methods=("triangulation", "ekf"), time_offset="off"))
    return clip


def test_c3d_residuals_and_camera_masks(exported, monkeypatch, capsys):
    import ezc3d

    rc, _, err = cli(monkeypatch, capsys, "export", exported, "--format", "c3d", "--predicted")
    assert rc == 0, err
    rig = Clip(exported).rig()
    for method in ("triangulation", "ekf"):
        c3d = ezc3d.c3d(str(exported / "out" / "export" / f"{method}.c3d"))
        labels = list(c3d["parameters"]["POINT"]["LABELS"]["value"])
        residual = c3d["data"]["meta_points"]["residuals"][0]  # markers × frames
        mask = c3d["data"]["meta_points"]["camera_masks"]  # 7 × markers × frames
        est = read_csv(exported / "out" / "estimates" / f"{method}.csv", ["frame", "marker", "x", "y", "z", "predicted"])
        det = read_csv(exported / "out" / "detections.csv", ["frame", "camera", "marker", "u", "v"])
        checked = 0
        for k, name, x, y, z, held in zip(est["frame"].astype(int), est["marker"], est["x"], est["y"], est["z"],
                                          est["predicted"], strict=True):
            i, r = labels.index(str(name)), residual[labels.index(str(name)), k]
            if not np.isfinite(x):
                assert r == -1
            elif held == 1:
                assert r == 0 and not mask[:, i, k].any()
            else:
                rows = (det["frame"] == k) & (det["marker"] == name)
                cams = {"left": 0, "right": 1}
                seen = {cams[str(c)]: (u, v) for c, u, v in zip(det["camera"][rows], det["u"][rows], det["v"][rows],
                                                               strict=True)}
                assert mask[:, i, k].tolist() == [c in seen for c in range(7)], (method, name, k)
                assert (k in GONE) == (0 not in seen)
                X = np.array([x, y, z])
                # independent: the reprojection error scaled to metres at the point's depth
                approx = np.mean([np.linalg.norm(rig.cameras[c].project(X[None])[0] - uv) * rig.cameras[c].depth(X)
                                  / rig.cameras[c].K[0, 0] for c, uv in seen.items()])
                assert r > 0 and abs(r - np.clip(approx, 1e-4, 0.0255)) <= 0.05 * approx + 1e-4, (method, name, k, r, approx)
                checked += 1
        assert checked >= 60  # of the 80 points (40 frames, two markers): the rest held or before the start


def test_c3d_without_the_detections_says_what_it_left_out(exported, tmp_path, monkeypatch, capsys):
    """detections.csv gone after the estimate: the C3D is still written, every measured point with
    the smallest positive residual and no camera mask, and a warning says why."""
    import ezc3d

    clip = tmp_path / "clip"
    shutil.copytree(exported, clip)
    (clip / "out" / "detections.csv").unlink()
    rc, _, err = cli(monkeypatch, capsys, "export", clip, "--format", "c3d", "--methods", "ekf")
    assert rc == 0, err
    assert "residuals and camera masks left unknown" in err and "detections.csv" in err
    c3d = ezc3d.c3d(str(clip / "out" / "export" / "ekf.c3d"))
    r = c3d["data"]["meta_points"]["residuals"][0]
    assert np.all(np.isin(np.round(r[r > 0], 6), [1e-4])) and (r > 0).sum() > 60
    assert not c3d["data"]["meta_points"]["camera_masks"].any()
