"""A smoother run after its filter under :func:`filter_passes_shared` smooths the filter's tracks
instead of filtering the observations again: the same numbers as the smoother alone (#42)."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.estimators import create
from pipeline.estimators.base import Track
from pipeline.estimators.kalman_common import filter_passes_shared


def hard_observations(rig, X) -> np.ndarray:
    """Noisy detections with what makes a filter's pass branch: a one-camera stretch, a gap of
    both cameras, a lone outlier and a run of them long enough to restart the track."""
    rng = np.random.default_rng(4)
    Y = rig.project(X) + rng.normal(0.0, 1.0, (len(X), 4))
    Y[40:70, 2:] = np.nan
    Y[100:104] = np.nan
    Y[130, :2] += 80.0
    Y[180:192, 2:] += 60.0
    return Y


def assert_same_track(a: Track, b: Track) -> None:
    """Every array of the two tracks equal to the last bit (NaN where NaN), timing aside."""
    for name in ("position", "velocity", "reprojection_error", "predicted", "covariance", "nis", "nis_dof"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.extra.keys() == b.extra.keys()
    for key in a.extra:
        np.testing.assert_array_equal(a.extra[key], b.extra[key], err_msg=key)


@pytest.mark.parametrize("filt", ["kf3d", "ekf"])
def test_a_smoother_after_its_filter_is_the_smoother_alone(receding, filt):
    """The pair's smoothed track equals the smoother's own run, bit for bit, and it is the filter's
    pass that was smoothed (its timing is the filter's, which a second pass would not repeat); the
    filter's caller masking its track in place changes nothing of what the smoother takes."""
    rig, dt, X, _ = receding
    Y = hard_observations(rig, X)
    alone = create(f"{filt}_rts", rig, dt, {}).run(Y)
    assert np.nansum(alone.extra["restart"]) >= 1 and alone.predicted[100:104].all()  # the branches ran
    with filter_passes_shared():
        filtered = create(filt, rig, dt, {}).run(Y)
        filtered.position[:50] = np.nan  # what association.filter_tracks does to a track's frames before its birth
        shared = create(f"{filt}_rts", rig, dt, {}).run(Y)
    assert shared.method == f"{filt}_rts" and shared.seconds_per_step == filtered.seconds_per_step
    assert_same_track(shared, alone)
    assert not np.array_equal(shared.position[60:], filtered.position[60:])  # smoothed, not the filter's


def test_a_smoother_with_other_settings_or_observations_filters_them_itself(receding):
    """Nothing is shared across different settings or different observations, nor outside the block."""
    rig, dt, X, _ = receding
    Y = hard_observations(rig, X)
    other = Y.copy()
    other[5, 0] += 0.5
    with filter_passes_shared():
        filtered = create("kf3d", rig, dt, {}).run(Y)
        noisier = create("kf3d_rts", rig, dt, {"process_noise": 3.0}).run(Y)
        moved = create("kf3d_rts", rig, dt, {}).run(other)
    assert noisier.seconds_per_step != filtered.seconds_per_step != moved.seconds_per_step
    assert_same_track(noisier, create("kf3d_rts", rig, dt, {"process_noise": 3.0}).run(Y))
    assert_same_track(moved, create("kf3d_rts", rig, dt, {}).run(other))
    assert create("kf3d_rts", rig, dt, {}).run(Y).seconds_per_step != filtered.seconds_per_step


def test_a_thread_sees_only_its_own_passes(receding):
    """Clips estimated in threads (a Dask worker's) share nothing: a smoother in another thread,
    outside a block of its own, filters the observations itself."""
    import threading

    rig, dt, X, _ = receding
    Y = hard_observations(rig, X)
    out = {}
    with filter_passes_shared():
        filtered = create("kf3d", rig, dt, {}).run(Y)
        other = threading.Thread(target=lambda: out.update(t=create("kf3d_rts", rig, dt, {}).run(Y)))
        other.start()
        other.join()
        here = create("kf3d_rts", rig, dt, {}).run(Y)
    assert here.seconds_per_step == filtered.seconds_per_step != out["t"].seconds_per_step
    assert_same_track(out["t"], here)
