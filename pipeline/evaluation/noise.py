"""The detections' pixel noise estimated from the data, for the methods that model it and were not
told one."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import StereoRig
from pipeline.core.chi2 import gammaincinv
from pipeline.core.rig import Rig


def estimate_view_sigma(rig: Rig, observations: dict[str, np.ndarray]) -> float | None:
    """Detection noise (px) of a :class:`Rig`'s cameras: the DLT over the k cameras that see a point leaves
    ``2k − 3`` degrees of freedom, so the summed squared reprojection residual is ``σ² χ²(2k − 3)``.
    Over the frames with the commonest k, σ̂² is the residuals' median over χ²(2k − 3)'s median: a
    median, so that one camera's outliers (a fifth of the frames, say) do not inflate it. χ²(d)'s median
    is ``2 P⁻¹(d/2, ½)`` (the inverse regularised lower incomplete gamma function), as scipy.stats
    computes it, without its import (:mod:`pipeline.core.chi2`)."""
    per_k: dict[int, list[np.ndarray]] = {}
    for Y in observations.values():
        seen = np.isfinite(Y).reshape(len(Y), rig.n, 2).all(axis=2)
        k = seen.sum(axis=1)
        ok = k >= 2
        if not ok.any():
            continue
        X = rig.triangulate(Y[ok])
        with np.errstate(invalid="ignore"):
            r2 = np.nansum((rig.project(X) - Y[ok]) ** 2, axis=1)
        good = np.all(np.isfinite(X), axis=1)
        for kk in np.unique(k[ok][good]):
            per_k.setdefault(int(kk), []).append(r2[good][k[ok][good] == kk])
    if not per_k:
        return None
    k = max(per_k, key=lambda kk: sum(len(a) for a in per_k[kk]))
    r2 = np.concatenate(per_k[k])
    return float(max(np.sqrt(np.median(r2) / (2 * gammaincinv((2 * k - 3) / 2, 0.5))), 0.02))


def estimate_pixel_sigma(rig: StereoRig | Rig, observations: dict[str, np.ndarray]) -> float | None:
    """Detection noise (px) from the data, for the methods that model it and were not told one:
    :func:`estimate_view_sigma` (a stereo pair as a rig of two). A median, not a mean: one camera's
    outliers (5 % of the frames, say) left a trimmed mean at ten times the noise, and every gate
    scaled by it wide open."""
    return estimate_view_sigma(rig if isinstance(rig, Rig) else Rig.from_stereo(rig), observations)
