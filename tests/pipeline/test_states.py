"""Track-state lanes (pipeline.present.states): what a filter did at each frame."""

from __future__ import annotations

import numpy as np

from pipeline.present.states import frame_states, transitions


def test_states_follow_the_tracks_flags_and_gaps():
    n = 14
    pos = np.zeros((n, 3))
    pos[:2] = np.nan  # not started
    pos[12:] = np.nan  # ended
    pred = np.zeros(n, dtype=bool)
    pred[:2] = pred[5:7] = True
    gated, restart = np.zeros(n), np.zeros(n)
    gated[8], restart[10] = 1.0, 1.0
    states = frame_states(pos, pred, {"gated": gated, "restart": restart})
    assert states == ["", "", "measured", "measured", "measured", "predicting", "predicting", "measured", "camera gated",
                      "measured", "restarted", "measured", "", ""]
    frames, values = transitions(states)
    assert frames.tolist() == [2, 5, 7, 8, 9, 10, 11, 12]
    assert values == ["measured", "predicting", "measured", "camera gated", "measured", "restarted", "measured", ""]


def test_a_track_without_gate_records_is_measured_or_predicting():
    pos = np.zeros((4, 3))
    states = frame_states(pos, np.array([False, True, True, False]), {})
    assert states == ["measured", "predicting", "predicting", "measured"]
    frames, values = transitions(["", ""])  # never an estimate: no lane at all
    assert not len(frames) and values == []
