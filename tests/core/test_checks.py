"""The input checks of pipeline.core.checks on constructed detections (no footage)."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.checks import stereo_checks

RIG = StereoRig.from_parameters(640, 480, (600.0, 600.0), (319.5, 239.5), 0.3)


def test_points_behind_a_camera_are_never_a_passed_check():
    """#39 (smaller): with the videos swapped, 66 of 66 points behind a camera were reported
    ``behind_camera`` ok (the swap check carried the warning). Both checks fail now; correct
    detections pass both."""
    X = np.column_stack([np.linspace(-0.3, 0.3, 66), np.zeros(66), np.linspace(1.5, 3.0, 66)])
    Y = RIG.project(X)
    good = {c.name: c.ok for c in stereo_checks(RIG, {"red": Y})}
    assert good["left_right"] and good["behind_camera"]
    swapped = {c.name: c for c in stereo_checks(RIG, {"red": Y[:, [2, 3, 0, 1]]})}
    assert not swapped["left_right"].ok and not swapped["behind_camera"].ok
    assert swapped["behind_camera"].value == 66
