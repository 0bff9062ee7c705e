"""#42: the estimate stage's methods in forked worker processes write byte for byte what one
process writes (timings aside), through the library and the command line;
``run``'s recording holds the frames its cameras' workers encoded."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from detectors.stage import detect_clip
from pipeline.core.forked import can_fork
from pipeline.core.settings import RunSettings
from pipeline.estimate import EstimateResult, estimate_clip
from tests.helpers import untimed

pytestmark = pytest.mark.skipif(not can_fork(), reason="the platform does not fork (workers run in the caller)")

def assert_same_estimates(one: EstimateResult, two: EstimateResult) -> None:
    """Every estimates/*.csv byte-equal, metrics.json equal outside its timings, the same method order."""
    files = sorted(p.name for p in (one.out_dir / "estimates").iterdir())
    assert files and files == sorted(p.name for p in (two.out_dir / "estimates").iterdir())
    for name in files:
        assert (one.out_dir / "estimates" / name).read_bytes() == (two.out_dir / "estimates" / name).read_bytes(), name
    a, b = (json.loads((r.out_dir / "metrics.json").read_text()) for r in (one, two))
    assert list(a["methods"]) == list(b["methods"])
    assert untimed(a) == untimed(b)


@pytest.fixture(scope="module")
def target_detected(target_clip, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("workers") / "detected"
    detect_clip(target_clip, RunSettings(), out)
    return out


@pytest.mark.slow
def test_every_default_method_in_workers_writes_what_one_process_writes(target_clip, target_detected, tmp_path):
    """Point and four-point-target methods, the defaults of a target clip, one process against two
    and three workers."""
    one = estimate_clip(target_clip, RunSettings(), tmp_path / "one", in_dir=target_detected, workers=1)
    assert one.target_tracks and len(one.metrics["methods"]) > 10
    for workers in (2, 3):
        assert_same_estimates(one, estimate_clip(target_clip, RunSettings(), tmp_path / f"w{workers}",
                                                 in_dir=target_detected, workers=workers))


def _recorded_images(rrd: Path) -> list[tuple[str, int, bytes]]:
    """(entity, frame, JPEG) of every image a recording holds, in order."""
    from rerun.chunk import RrdReader

    rows = []
    for chunk in RrdReader(rrd).stream():
        if chunk.entity_path.endswith("/image"):
            batch = chunk.to_record_batch()
            for k, blob in zip(batch.column("frame").to_pylist(), batch.column("EncodedImage:blob").to_pylist(),
                               strict=True):
                rows.append((chunk.entity_path, k, bytes(blob[0] if isinstance(blob, list) else blob)))
    return sorted(rows)


@pytest.mark.parametrize("workers", [1, 2])
def test_run_s_recording_holds_each_frame_as_its_camera_encoded_it(mp4_clip, tmp_path, workers):
    """``run`` records the frames as JPEGs that each camera's detection worker makes (a process of
    its own with two workers): the recording holds every frame of both cameras, each the JPEG of
    that decoded frame at the recorder's quality, and the detections are those of a plain
    ``detect``."""
    import cv2

    from pipeline.app.run import process_clip
    from pipeline.core.frames import StereoFrameSource

    res = process_clip(mp4_clip, tmp_path / "run", RunSettings(methods=["triangulation"], figures=False),
                       workers=workers)
    assert res.recording is not None
    want = sorted((f"/world/{cam}/image", fr.index, cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])[1].tobytes())
                  for fr in StereoFrameSource(mp4_clip) for cam, img in zip(("left", "right"), fr.images, strict=True))
    assert _recorded_images(res.recording) == want
    detect_clip(mp4_clip, RunSettings(), tmp_path / "plain")
    assert (tmp_path / "run" / "detections.csv").read_bytes() == (tmp_path / "plain" / "detections.csv").read_bytes()


def test_jobs_pair_smoothers_with_filters_and_share_costly_imports():
    """The default methods' jobs: each smoother with its filter, the methods importing scipy's
    expm kernel (the target's) together, the UKF (numpy's Cholesky) apart; every method once. A smoother with its
    own settings runs apart."""
    from pipeline.estimate import _jobs
    from pipeline.estimators.registration import default_methods

    methods = default_methods(True)
    jobs = _jobs(methods, {})
    assert sorted(m for job in jobs for m in job) == sorted(methods)
    assert ("kf3d", "kf3d_rts") in jobs and ("ekf", "ekf_rts") in jobs
    assert {"kalman_bucy", "pnp_kf"} in [set(job) for job in jobs] and ("ukf",) in jobs
    apart = _jobs(["kf3d", "kf3d_rts"], {"kf3d_rts": {"process_noise": 2.0}})
    assert apart == [("kf3d",), ("kf3d_rts",)]


@pytest.mark.parametrize("workers", [1, 2])
def test_methods_run_in_shared_jobs_write_what_each_writes_alone(target_clip, target_detected, tmp_path, workers):
    """A smoother after its filter (one forward pass) and the methods after the target's (run first,
    taken in the asked order) write the bytes each writes when run alone, and metrics.json keeps the asked order."""
    asked = ["ukf", "kf3d", "kf3d_rts", "kalman_bucy"]
    together = estimate_clip(target_clip, RunSettings(methods=asked), tmp_path / "together", in_dir=target_detected,
                             workers=workers)
    assert list(together.metrics["methods"]) == ["ukf", "kf3d", "kf3d_rts", "kalman_bucy"]
    for m in asked:
        alone = estimate_clip(target_clip, RunSettings(methods=[m]), tmp_path / m, in_dir=target_detected)
        name = f"estimates/{m}.csv"
        assert (together.out_dir / name).read_bytes() == (alone.out_dir / name).read_bytes(), m
        assert untimed(together.metrics["methods"][m]) == untimed(alone.metrics["methods"][m]), m
