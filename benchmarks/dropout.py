"""A 60-frame one-camera drop-out (frames 100–159; the left camera on even seeds, the right on odd)
against the same clip without it: the Kalman family's peak 3-D error over the 40 frames after the
camera returns, over the clean run's RMSE, beside the clean run's own peak over those frames (the
same ratio with no drop-out at all: what a peak over 40 frames is for that filter on that motion).

    python benchmarks/dropout.py [--seeds 8] [--write-docs]

Observations simulated from the scenario's truth (1 px Gaussian noise), 300 frames, every layout of
the second camera; the method as ``create`` gives it at its defaults, with σ estimated from each
clip's observations (what ``stereotrack estimate`` does), then with σ given (1 px).
"""

from __future__ import annotations

import argparse
import statistics

import numpy as np
from _common import LiveDoc, page

from pipeline.estimators import create
from pipeline.evaluation.noise import estimate_pixel_sigma
from renderers.motion import simulate_truth
from renderers.scenario import load_scenario, parse_scenario

LAYOUTS = {"right": {"position": [0.3, 0, 0]}, "left": {"position": [-0.3, 0, 0]}, "above": {"position": [0, -0.3, 0]},
           "below": {"position": [0, 0.3, 0]}, "diagonal": {"position": [0.25, -0.2, 0.02], "rotation_deg": [0, -3, 4]}}
METHODS = ("kf3d", "ekf", "ukf", "kf3d_rts", "ekf_rts", "ekf_imm")
GAP, AFTER = (100, 160), 40


def scene(name: str, layout: str):
    """The scenario's truth and rig, its second camera moved to ``layout``."""
    d = load_scenario(name).with_overrides(frames=300).model_dump(mode="json")
    d["rig"]["right"], d["rig"]["toe_in_deg"] = LAYOUTS[layout], 0.0
    s = parse_scenario(d)
    return s.dt, simulate_truth(s).positions[:, 0], s.rig.build()


def ratios(method: str, dt: float, X: np.ndarray, rig, seed: int, given: bool) -> tuple[float, float]:
    """(peak after the return ÷ clean RMSE, the clean run's peak there ÷ clean RMSE) for one seed;
    σ given (1 px), or estimated from each clip's observations as ``stereotrack estimate`` does."""
    Y = rig.project(X) + np.random.default_rng(seed).normal(0, 1.0, (len(X), 4))
    Yg = Y.copy()
    Yg[GAP[0] : GAP[1], 2 * (seed % 2) : 2 * (seed % 2) + 2] = np.nan

    def errors(obs: np.ndarray) -> np.ndarray:
        sigma = 1.0 if given else estimate_pixel_sigma(rig, {"m": obs})
        return np.linalg.norm(create(method, rig, dt, {"pixel_sigma": sigma}).run(obs).position - X, axis=1)

    gap, clean = errors(Yg), errors(Y)
    rmse = float(np.sqrt(np.nanmean(clean**2)))
    after = slice(GAP[1], GAP[1] + AFTER)
    return float(np.max(gap[after])) / rmse, float(np.max(clean[after])) / rmse


def table(md: LiveDoc, seeds: int, given: bool) -> None:
    """One table (σ given or estimated) and the sentence summarising it."""
    md += ["", f"## σ {'given (1 px)' if given else 'estimated from the observations, as `stereotrack estimate` does'}", "",
           "| motion | layout | " + " | ".join(METHODS) + " |", "|---|---|" + "---:|" * len(METHODS)]
    worst: dict[str, list[float]] = {m: [] for m in METHODS}
    clean_peak: dict[str, list[float]] = {m: [] for m in METHODS}
    excess: dict[str, list[float]] = {m: [] for m in METHODS}
    for name in ("maneuvering", "sine", "receding"):
        for layout in LAYOUTS:
            dt, X, rig = scene(name, layout)
            cells = []
            for m in METHODS:
                got = [ratios(m, dt, X, rig, seed, given) for seed in range(seeds)]
                g, c = [r[0] for r in got], [r[1] for r in got]
                worst[m].append(statistics.median(g))
                clean_peak[m].append(statistics.median(c))
                excess[m].append(statistics.median(g) / statistics.median(c))
                cells.append(f"{statistics.median(g):.2f} ({max(g):.2f}) [{statistics.median(c):.2f}]")
            md.append(f"| {name} | {layout} | " + " | ".join(cells) + " |")
    md += ["", "Per method over the 15 cells: the median ratio ranges " + ", ".join(
        f"{m} {min(v):.2f}–{max(v):.2f}" for m, v in worst.items()) + "; the clean run's own peak "
        + ", ".join(f"{m} {min(v):.2f}–{max(v):.2f}" for m, v in clean_peak.items())
        + "; the drop-out's median over the clean run's, at most " + ", ".join(
        f"{m} {max(v):.2f}" for m, v in excess.items()) + ". One seed set."]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=8)
    args = ap.parse_args()
    md = LiveDoc(["# A 60-frame one-camera drop-out", "",
                  f"Peak 3-D error over the {AFTER} frames after one camera returns from a {GAP[1] - GAP[0]}-frame "
                  "drop-out, over the same clip's clean RMSE: median (worst) over "
                  f"{args.seeds} seeds; beside it, in brackets, the clean run's own peak over the same frames, "
                  "over its RMSE (median). 1 px noise, 300 frames at each scenario's rate."])
    table(md, args.seeds, given=False)
    table(md, args.seeds, given=True)


if __name__ == "__main__":
    page("dropout", main)
