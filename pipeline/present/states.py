"""Each track's state frame by frame, as lanes for rerun's state timeline: when a filter measured,
when it only predicted (a gap, or every camera gated), when its gate dropped a camera, when it
restarted, and when it had no estimate at all (before its start, after a track ends). The lanes
show what the tables only count."""

from __future__ import annotations

import numpy as np

#: the states, in the order a legend lists them, with their colours (RGB): measured green, one camera
#: gated amber, predicting grey-blue, restarted red; no estimate is a gap in the lane
STATES: dict[str, tuple[int, int, int]] = {
    "measured": (46, 160, 67),
    "camera gated": (230, 160, 30),
    "predicting": (120, 140, 170),
    "restarted": (214, 39, 40),
}


def frame_states(position: np.ndarray, predicted: np.ndarray, extra: dict[str, np.ndarray]) -> list[str]:
    """The state of a track at every frame ("" where it has no estimate): restarted, else predicting
    (no measurement used), else camera gated (a camera dropped by the gate), else measured."""
    n = len(position)
    have = np.all(np.isfinite(position), axis=1)
    gated = np.nan_to_num(np.asarray(extra.get("gated", np.zeros(n)), dtype=float).reshape(-1)[:n]) > 0
    restart = np.nan_to_num(np.asarray(extra.get("restart", np.zeros(n)), dtype=float).reshape(-1)[:n]) > 0
    pred = np.asarray(predicted, dtype=bool)[:n]
    out = np.where(restart, "restarted", np.where(pred, "predicting", np.where(gated, "camera gated", "measured")))
    return [s if h else "" for s, h in zip(out.tolist(), have.tolist(), strict=True)]


def transitions(states: list[str]) -> tuple[np.ndarray, list[str]]:
    """The frames where the state changes (the first frame with an estimate included) and the state
    entered there: what rerun's ``StateChange`` takes ("" resets the lane: a gap)."""
    frames, values, last = [], [], ""
    for k, s in enumerate(states):
        if s != last:
            frames.append(k)
            values.append(s)
            last = s
    return np.array(frames, dtype=np.int64), values
