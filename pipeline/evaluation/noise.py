"""The detections' pixel noise estimated from the data, for the methods that model it and were not
told one."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import StereoRig


def estimate_pixel_sigma(rig: StereoRig, observations: dict[str, np.ndarray]) -> float | None:
    """Detection noise (px) from the data: the DLT leaves one degree of freedom of the four
    stereo coordinates, so the squared reprojection residual of a triangulated point is
    ``σ² χ²(1)``; σ̂² is its mean over all frames and markers. None without stereo frames."""
    from pipeline.core.camera import triangulate

    sq = []
    for Y in observations.values():
        ok = np.all(np.isfinite(Y), axis=1)
        if ok.any():
            X = triangulate(rig, Y[ok])
            good = np.all(np.isfinite(X), axis=1)
            r = rig.project(X[good]) - Y[ok][good]
            sq.append(np.sum(r**2, axis=1))
    if not sq:
        return None
    allsq = np.concatenate(sq)
    # a robust mean: drop the worst 2 % (mislabelled or occluded frames)
    allsq = np.sort(allsq)[: max(1, int(0.98 * len(allsq)))]
    return float(max(np.sqrt(np.mean(allsq)), 0.02))
