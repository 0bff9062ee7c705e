"""Projected truth: each marker's pixel coordinates and visibility in both cameras, and the
``truth.csv`` / ``target_truth.csv`` tables of SPEC §3."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.camera import StereoRig
from pipeline.clip import TARGET_TRUTH_COLUMNS, TRUTH_COLUMNS
from pipeline.io import write_csv
from renderers.motion import Truth, distractor_positions
from renderers.scenario import Scenario

NEAR = 0.05  # metres; closer than this counts as not in front of the camera


@dataclass
class ProjectedTruth:
    """``uv``: frames × markers × 4 (left u, v, right u, v); ``visible``: frames × markers × 2."""

    uv: np.ndarray
    visible: np.ndarray


def _occluders(scenario: Scenario, truth: Truth) -> list[tuple[np.ndarray, float, int | None]]:
    """Occluding spheres (centre per frame, radius, marker index or None for distractors)."""
    occ: list[tuple[np.ndarray, float, int | None]] = [
        (truth.positions[:, i], float(truth.radii[i]), i) for i in range(len(truth.names))
    ]
    dpos = distractor_positions(scenario)
    for j, d in enumerate(scenario.distractors):
        r = d.size * (np.sqrt(3) / 2 if d.shape == "cube" else 0.5)
        occ.append((dpos[:, j], float(r), None))
    return occ


def project_truth(rig: StereoRig, scenario: Scenario, truth: Truth) -> ProjectedTruth:
    """Project every marker into both cameras and decide visibility: in front of the camera, centre
    inside the image, facing the camera (flat target markers) and not hidden behind another
    object (markers, distractors, the target plate)."""
    n, m = truth.positions.shape[:2]
    uv = np.empty((n, m, 4))
    visible = np.zeros((n, m, 2), dtype=bool)
    occluders = _occluders(scenario, truth)
    for c, cam in enumerate(rig.cameras):
        C = cam.center
        for i in range(m):
            p = truth.positions[:, i]
            uv[:, i, 2 * c : 2 * c + 2] = cam.project(p)
            vis = (cam.depth(p) > NEAR) & rig.in_image(uv[:, i, 2 * c : 2 * c + 2])
            nrm = truth.normals[:, i]
            if np.all(np.isfinite(nrm)):
                vis &= np.einsum("ij,ij->i", nrm, C - p) > 0
            seg = p - C
            seg_len2 = np.einsum("ij,ij->i", seg, seg)
            for q, r, j in occluders:
                if j == i:
                    continue
                s = np.clip(np.einsum("ij,ij->i", q - C, seg) / seg_len2, 0.0, 1.0)
                closest = C + s[:, None] * seg
                dist = np.linalg.norm(q - closest, axis=1)
                vis &= ~((dist < r + truth.radii[i]) & (s < 1.0 - 1e-9))
            for tgt in truth.targets:
                if truth.names[i].startswith(tgt.name + "_"):
                    continue  # the target's own markers lie on its face
                # segment ∩ plate plane, inside the (square) plate
                denom = np.einsum("ij,ij->i", tgt.normal, seg)
                with np.errstate(divide="ignore", invalid="ignore"):
                    s = np.einsum("ij,ij->i", tgt.normal, tgt.center - C) / denom
                hit = C + s[:, None] * seg
                half = 1.4 * tgt.radius
                off = hit - tgt.center
                inside = np.max(np.abs(off), axis=1) < half * 1.5  # conservative (plate is rotated)
                vis &= ~((s > 0) & (s < 1) & inside)
            visible[:, i, c] = vis
    return ProjectedTruth(uv, visible)


def write_truth(path: Path, truth: Truth, proj: ProjectedTruth) -> None:
    """Write ``truth.csv`` (long format, one row per frame per marker)."""

    def rows():
        for k in range(truth.n_frames):
            for i, name in enumerate(truth.names):
                yield (
                    k, truth.t[k], name, *truth.positions[k, i], *truth.velocities[k, i],
                    *proj.uv[k, i], int(proj.visible[k, i, 0]), int(proj.visible[k, i, 1]),
                )

    write_csv(path, TRUTH_COLUMNS, rows())


def write_target_truth(path: Path, truth: Truth, proj: ProjectedTruth) -> None:
    """Write ``target_truth.csv`` for the (single) four-point target."""
    tgt = truth.targets[0]
    idx = [truth.names.index(f"{tgt.name}_{j}") for j in range(1, 5)]

    def rows():
        for k in range(truth.n_frames):
            px = [proj.uv[k, i, 2 * c + d] for c in range(2) for i in idx for d in range(2)]
            yield (k, truth.t[k], tgt.alpha[k], tgt.alpha_dot[k], tgt.distance[k], tgt.distance_dot[k], tgt.axis_angle, *px)

    write_csv(path, TARGET_TRUTH_COLUMNS, rows())
