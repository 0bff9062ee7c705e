"""The 3-D view's framing (pipeline.present.layout.framing) on paths of different shapes and places."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.present.layout import FILL, _labels_apart, _moments, _project, framing

t = np.linspace(0.0, 1.0, 200)[:, None]
PATHS = {
    "receding": np.hstack([-0.3 + 1.5 * t, 0.1 - 0.5 * t, 1.6 + 3.0 * t]),  # the default scenario's red marker
    "across": np.hstack([-1.0 + 2.0 * t, 0 * t, 2.5 + 0 * t]),
    "circle": np.hstack([0.4 * np.cos(6.3 * t), 0.2 * np.sin(6.3 * t), 2.0 + 0.4 * np.sin(6.3 * t)]),
    "two apart": [np.hstack([-0.8 + 0.2 * t, 0 * t, 1.5 + 0 * t]), np.hstack([0.6 + 0.2 * t, -0.3 + 0 * t, 4.0 + 0.5 * t])],
    # a four-point target facing the cameras and receding (the plate seen edge on piles its labels up)
    "target": [np.hstack([0.1 * np.cos(a) + 0 * t, 0.1 * np.sin(a) + 0 * t, 1.8 + 0.4 * t]) for a in (0, 1.57, 3.14, 4.71)],
    "far right": np.hstack([2.0 + 0.1 * t, 0.5 + 0 * t, 6.0 + 0.4 * t]),
}


@pytest.mark.parametrize("name", PATHS)
def test_the_paths_fill_the_view_and_stay_in_it(name):
    """Every point in front of the eye and inside the view, the image centred, and across at least
    0.4 of the view in its longer direction (the acceptance asks a third; a long path reaches FILL,
    a compact one stops where its nearest point would come closer than NEAR), looking down."""
    paths = PATHS[name] if isinstance(PATHS[name], list) else [PATHS[name]]
    eye, target = framing(paths)
    ndc, depth = _project(np.vstack(paths), eye, target)
    assert depth.min() > 0 and np.abs(ndc).max() <= FILL + 1e-6, (ndc.min(axis=0), ndc.max(axis=0))
    assert np.ptp(ndc, axis=0).max() >= 0.8, np.ptp(ndc, axis=0)  # 0.4 of the view; 0.85 for a long path
    np.testing.assert_allclose((ndc.min(axis=0) + ndc.max(axis=0)) / 2, 0.0, atol=0.02)
    assert eye[1] < target[1]  # looking down (y is down)
    assert _labels_apart(_moments(paths), eye, target)


def test_too_few_points_have_no_framing():
    assert framing([np.array([[np.nan, 0.0, 1.0], [0.0, 0.0, 2.0]])]) is None
    assert framing([]) is None
