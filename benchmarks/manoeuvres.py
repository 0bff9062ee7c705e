"""A marker that cruises and turns hard, and smooth motion beside it: the IMM EKF against the EKF
(one process noise), triangulation, ``spsa_stereo`` and the predict-only baseline, each at its
defaults from the shared initiator, on simulated detections (1 px noise, a camera that does not see
the marker gives nothing).

    python benchmarks/manoeuvres.py [--seeds 10-14] [--frames 300] [--write-docs]

Paths from ``renderers.paths`` (``turning``: 3–8-frame turns at 8–14 m/s²; ``sinusoid``); rigs
640×480, f = 600 px, the second camera 0.3 m above or left of the first. The figures are medians
over the seeds with the range in brackets; NEES per degree of freedom is the median position NEES
over χ²₃'s median (1 for a consistent filter).
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np
from _common import page

from pipeline.core.camera import Camera, StereoRig
from pipeline.estimators import create
from renderers.paths import observed, sinusoid, turning

DT = 1 / 30
BASE = StereoRig.from_parameters(640, 480, (600.0, 600.0), (319.5, 239.5), 0.3)
RIGS = {"above": StereoRig(BASE.left, Camera(BASE.left.K, np.eye(3), np.array([0.0, 0.3, 0.0])), BASE.image_size),
        "left": StereoRig(BASE.left, Camera(BASE.left.K, np.eye(3), np.array([0.3, 0.0, 0.0])), BASE.image_size)}
METHODS = ("ekf_imm", "ekf", "triangulation", "spsa_stereo", "predict_only")
CHI2_3_MEDIAN = 2.365973884375338


def scores(track, X: np.ndarray) -> tuple[float, float]:
    """(3-D RMSE in mm from the sixth frame, NEES per degree of freedom or NaN without a covariance)."""
    e = track.position - X
    rmse = 1000 * float(np.sqrt(np.nanmean(np.sum(e[5:] ** 2, axis=1))))
    if track.covariance is None:
        return rmse, float("nan")
    C = track.covariance[:, :3, :3]
    ok = np.isfinite(e).all(axis=1) & np.isfinite(C).all(axis=(1, 2))
    nees = [d @ np.linalg.solve(c, d) for d, c in zip(e[ok][5:], C[ok][5:], strict=True)]
    return rmse, float(np.median(nees)) / CHI2_3_MEDIAN


def spread(v: list[float], fmt: str = ".1f") -> str:
    v = [x for x in v if np.isfinite(x)]
    return f"{statistics.median(v):{fmt}} ({min(v):{fmt}}–{max(v):{fmt}})" if v else "—"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", default="10-14")
    ap.add_argument("--frames", type=int, default=300)
    args = ap.parse_args()
    lo, hi = (int(s) for s in args.seeds.split("-"))
    print(f"# Manoeuvring markers\n\n{args.frames} frames at 30 fps, seeds {lo}–{hi}, 1 px noise; 3-D RMSE (mm) "
          "and NEES per degree of freedom, median (range) over the seeds.\n")
    print("| motion | layout | method | 3-D RMSE (mm) | NEES / dof |")
    print("|---|---|---|---:|---:|")
    for motion in ("turning", "sinusoid"):
        for layout, rig in RIGS.items():
            got: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
            for seed in range(lo, hi + 1):
                X = turning(args.frames, seed, DT)[0] if motion == "turning" else sinusoid(args.frames, seed, DT)
                Y = observed(rig, X, seed)
                for m in METHODS:
                    got[m].append(scores(create(m, rig, DT).run(Y), X))
            for m in METHODS:
                print(f"| {motion} | {layout} | `{m}` | {spread([r for r, _ in got[m]])} | "
                      f"{spread([n for _, n in got[m]], '.2f')} |")


if __name__ == "__main__":
    page("manoeuvres", main)
