"""What was computed from one observation, remembered by the observation's bytes.

Every method of an estimate stage, and the gates within one method's step, triangulate the same
frame's detections again; a rig remembers each single observation's point
(:meth:`~pipeline.core.camera.StereoRig.triangulate`)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


class RowMemo:
    """``fn(row)`` of single rows, remembered by the row's bytes: at most ``size`` of them (a full
    memo starts again). What it returns is a copy: a caller changing it changes nothing
    remembered. It pickles empty (a rig sent to a worker process carries its cameras, not this)."""

    def __init__(self, size: int) -> None:
        self.size = size
        self.rows: dict[bytes, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.rows)

    def get(self, row: np.ndarray, fn: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        key = row.tobytes()
        out = self.rows.get(key)
        if out is None:
            out = fn(row)
            if len(self.rows) >= self.size:
                self.rows.clear()
            self.rows[key] = out
        return out.copy()

    def fill(self, rows: np.ndarray, outs: np.ndarray) -> None:
        """Remember ``outs[i]`` as what ``fn(rows[i])`` gives, up to ``size`` rows."""
        for row, out in zip(rows, outs, strict=True):
            if len(self.rows) >= self.size:
                return
            self.rows.setdefault(row.tobytes(), out)

    def __getstate__(self) -> dict:
        return {"size": self.size, "rows": {}}
