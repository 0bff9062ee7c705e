"""The rectifying frame of a stereo pair (Bouguet's rotation: the second camera on its x axis) and
each camera's normalized projection in it, for the estimators that work in disparity."""

from __future__ import annotations

import numpy as np

from pipeline.core.camera import StereoRig


def rectifying_frame(rig: StereoRig) -> tuple[np.ndarray, np.ndarray]:
    """``(R, t)``: world → a frame at the left camera whose x axis points along the baseline, to the
    second camera wherever it sits (right, left, above, below, diagonal), and whose z axis stays
    close to the left optical axis — Bouguet's rectifying rotation (e₁ along the baseline,
    e₂ = (−e₁ᵧ, e₁ₓ, 0)/‖·‖, e₃ = e₁ × e₂; Bradski & Kaehler, *Learning OpenCV*, ch. 12). In it
    the second camera sits at (b, 0, 0), so ``q₂`` is its image x for any layout."""
    left = rig.left
    e1 = left.R @ rig.right.center + np.ravel(left.t)  # the second camera, in the left camera's frame
    e1 = e1 / np.linalg.norm(e1)
    e2 = np.array([-e1[1], e1[0], 0.0])
    e2 = e2 / np.linalg.norm(e2) if np.linalg.norm(e2) > 1e-9 else np.array([0.0, 1.0, 0.0])
    Rr = np.stack([e1, e2, np.cross(e1, e2)])
    return Rr @ left.R, Rr @ np.ravel(left.t)


def disparity_maps(rig: StereoRig) -> tuple[list[float], list[float]]:
    """Each camera's normalized projection as a 3×4 map of ``(s₀, s₁, 1, s₂)`` (row-major floats):
    ``[M_c | m_c / b]`` with ``M_c = R_c R₀ᵀ``, ``m_c = t_c − M_c t₀`` for the rectifying frame
    ``(R₀, t₀)`` of :func:`rectifying_frame`."""
    R0, t0 = rectifying_frame(rig)
    out = []
    for cam in rig.cameras:
        M = cam.R @ R0.T
        m = np.ravel(cam.t) - M @ t0
        out.append(np.hstack([M, (m / rig.baseline)[:, None]]).ravel().tolist())
    return out[0], out[1]
