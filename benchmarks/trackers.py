"""Every point method over simulated imperfect conditions and over the rendered imperfect-rig suite.

    python benchmarks/trackers.py [--seeds 5] [--seed-sets 3] [--suite simulated|imperfect|all]
                                  [--imperfect-frames 90] [--out DIR | --write-docs]

Simulated suite (``--suite simulated``, docs/trackers.md): the exact truth of four scenarios
(receding, maneuvering, accelerating, sine; 300 frames at their own rig and frame rate) projected
with 1 px Gaussian noise, under nine conditions: clean; 5 % of frames with one camera's detection
replaced by a random pixel; the right camera half a frame late; 40 % of frames seen by one camera
only; a 60-frame gap (both cameras, frames 120–179); and the second camera left, above, below or
diagonal (rotated) instead of right. Every method runs as ``stereotrack estimate`` runs it: from the
shared initiator on the observations (no truth, no true velocity), at its defaults (σ = 1 px, the
default, is the simulated noise), with the time offset estimated from the observations and applied
when its interval excludes zero (``--time-offset auto``). A run *diverged* when its RMSE from the
second frame on is more than 5× the RMSE of triangulation on the same seed's clean observations
(frames with an observation), or a started track is not finite. The predict-only row (the initiator's start,
no update) is every method's baseline.

Rendered suite (``--suite imperfect``, docs/trackers_imperfect.md): each imperfect scenario of
data/scenarios/ rendered and run through the pipeline itself (see :func:`imperfect_suite`).
"""

from __future__ import annotations

import argparse

import numpy as np
from _common import LiveDoc, add_output_args, output_dir

from pipeline.core.io import write_text
from pipeline.core.settings import RunSettings
from pipeline.core.sync import resolve_sync
from pipeline.estimators import create, methods
from renderers.motion import simulate_truth
from renderers.scenario import load_scenario, parse_scenario

SCENARIOS = ("receding", "maneuvering", "accelerating", "sine")
FRAMES = 300
LAYOUTS = {"left": {"position": [-0.3, 0, 0]}, "above": {"position": [0, -0.3, 0]}, "below": {"position": [0, 0.3, 0]},
           "diagonal": {"position": [0.25, -0.2, 0.02], "rotation_deg": [0, -3, 4]}}
CONDITIONS = ("clean", "outliers", "sync", "one_camera", "gap", *LAYOUTS)
CONDITION_TEXT = {"clean": "clean", "outliers": "5 % outliers", "sync": "½ frame late", "one_camera": "40 % one camera",
                  "gap": "60-frame gap", "left": "left", "above": "above", "below": "below", "diagonal": "diagonal"}


def setup(name: str, layout: str | None = None):
    """(rig, dt, fps, positions, positions half a frame later) of a scenario, with the second camera moved."""
    s = load_scenario(name).with_overrides(frames=FRAMES)
    if layout is not None:
        d = s.model_dump(mode="json")
        d["rig"]["right"], d["rig"]["toe_in_deg"] = LAYOUTS[layout], 0.0
        s = parse_scenario(d)
    tr = simulate_truth(s)
    late = tr.at(tr.t + 0.5 * s.dt, [0])[0][:, 0]
    return s.rig.build(), s.dt, 1.0 / s.dt, tr.positions[:, 0], late


def observe(condition: str, rig, X, late, rng) -> tuple[np.ndarray, np.ndarray]:
    """(observations under ``condition``, the same seed's clean observations)."""
    noise = rng.normal(0, 1.0, (len(X), 4))
    clean = rig.project(X) + noise
    Y = clean.copy()
    if condition == "outliers":
        w, h = rig.image_size
        for k in np.flatnonzero(rng.random(len(X)) < 0.05):
            c = rng.integers(0, 2)
            Y[k, 2 * c : 2 * c + 2] = rng.uniform([0, 0], [w, h])
    elif condition == "sync":
        Y[:, 2:] = rig.right.project(late) + noise[:, 2:]
    elif condition == "one_camera":
        for k in np.flatnonzero(rng.random(len(X)) < 0.4):
            c = rng.integers(0, 2)
            Y[k, 2 * c : 2 * c + 2] = np.nan
    elif condition == "gap":
        Y[120:180] = np.nan
    return Y, clean


def run_as_estimate(method: str, rig, dt: float, fps: float, Y: np.ndarray, sync) -> tuple:
    """A method on one marker as ``stereotrack estimate`` runs it (``sync``: resolve_sync's answer)."""
    _, aligned = sync  # every method sees the right camera re-timed when an offset is applied
    return create(method, rig, dt, {"seed": 0}).run(aligned["m"])


def make_runs(seeds: int, first_seed: int = 0) -> list[tuple]:
    """Every condition × scenario × seed (``first_seed`` on): (condition, scenario, rig, dt, fps,
    truth, observations, clean triangulation RMSE, sync, the outlier frames)."""
    runs = []
    for cond in CONDITIONS:
        for scen in SCENARIOS:
            rig, dt, fps, X, late = setup(scen, cond if cond in LAYOUTS else None)
            for seed in range(first_seed, first_seed + seeds):
                rng = np.random.default_rng(1000 * seed + 17 * CONDITIONS.index(cond) + SCENARIOS.index(scen))
                Y, clean = observe(cond, rig, X, late, rng)
                tri = create("triangulation", rig, dt).run(clean).position
                seen = np.isfinite(Y).any(axis=1)
                seen[0] = False
                tri_rmse = float(np.sqrt(np.nanmean(np.sum((tri[seen] - X[seen]) ** 2, axis=1))))
                bad = np.any(np.isfinite(Y) & (Y != clean), axis=1) if cond == "outliers" else None
                runs.append((cond, scen, rig, dt, fps, X, Y, tri_rmse, resolve_sync("auto", rig, {"m": Y}, fps), bad))
    return runs


def mean_rmse(m: str, runs: list[tuple]) -> dict[str, float]:
    """A method's mean 3-D RMSE per condition over ``runs`` (as the table's cells)."""
    rms: dict[str, list[float]] = {c: [] for c in CONDITIONS}
    for cond, _scen, rig, dt, fps, X, Y, _tri, sync, _bad in runs:
        e = np.linalg.norm(run_as_estimate(m, rig, dt, fps, Y, sync).position - X, axis=1)
        rms[cond].append(float(np.sqrt(np.nanmean(e[1:] ** 2))))
    return {c: float(np.mean(v)) for c, v in rms.items()}


def simulated_suite(seeds: int, out_dir, seed_sets: int = 3) -> None:
    """The table of docs/trackers.md (see the module docstring)."""
    names = [m for m in methods("point") if m != "predict_only"] + ["predict_only"]
    runs = make_runs(seeds)
    applied = sum(r[8][0].applied for r in runs if r[0] == "sync")
    false_alarms = sum(r[8][0].applied for r in runs if r[0] != "sync")
    by_cond = {c: sum(r[8][0].applied for r in runs if r[0] == c) for c in CONDITIONS if c != "sync"}
    where = ", ".join(f"{CONDITION_TEXT[c]} {v}" for c, v in by_cond.items() if v) or "none"
    n_cells = len(SCENARIOS) * seeds
    md = LiveDoc(["# Trackers under simulated imperfect conditions", "",
                  f"Generated by `python benchmarks/trackers.py --suite simulated --seeds {seeds} --seed-sets {seed_sets}`; "
                  "settings in its "
                  f"docstring. Each cell is the mean 3-D RMSE in mm over {n_cells} runs (4 scenarios × {seeds} seeds, "
                  f"{FRAMES} frames, 1 px noise), every method from the shared initiator at its defaults; "
                  "(n) counts the runs that diverged. *steps/s* is the median of `seconds_per_step` over all runs.", "",
                  f"Time offset: applied on {applied} of {n_cells} *½ frame late* runs and on {false_alarms} of "
                  f"{len(runs) - n_cells} others ({where}). RMSE is over frames 1 to the end, coasting through gaps "
                  "included; divergence is judged on the frames with an observation.", "",
                  "| method | " + " | ".join(CONDITION_TEXT[c] for c in CONDITIONS) + " | diverged | steps/s |",
                  "|---|" + "---:|" * (len(CONDITIONS) + 2)])
    table: dict[str, dict[str, float]] = {}
    gating: dict[str, list[int]] = {}
    for m in names:
        rms: dict[str, list] = {c: [] for c in CONDITIONS}
        div: dict[str, int] = dict.fromkeys(CONDITIONS, 0)
        sps = []
        gating[m] = [0, 0, 0, 0, 0]  # outliers rejected, injected; clean observations rejected, observed; restarts
        for cond, _scen, rig, dt, fps, X, Y, tri_rmse, sync, bad in runs:
            tr = run_as_estimate(m, rig, dt, fps, Y, sync)
            count_gating(gating[m], cond, tr, bad)
            e = np.linalg.norm(tr.position - X, axis=1)
            started = np.isfinite(tr.position).all(axis=1).argmax() if np.isfinite(tr.position).any() else len(X)
            r = float(np.sqrt(np.nanmean(e[1:] ** 2)))
            seen = np.isfinite(Y).any(axis=1)
            seen[0] = False  # divergence from the second frame on, on frames with an observation
            lost = not np.all(np.isfinite(e[started:])) or not np.sqrt(np.nanmean(e[seen] ** 2)) <= 5 * tri_rmse
            div[cond] += int(lost)
            rms[cond].append(r)
            sps.append(tr.seconds_per_step)
        table[m] = {c: float(np.mean(v)) for c, v in rms.items()}
        cells = [f"{1000 * table[m][c]:.1f}" + (f" ({div[c]})" if div[c] else "") for c in CONDITIONS]
        md.append(f"| {m} | " + " | ".join(cells) + f" | {sum(div.values())} of {len(runs)} | "
                  f"{1 / np.median(sps):,.0f} |")
    others = []  # the summary's three methods on the other seed sets
    for k in range(1, seed_sets):
        more = make_runs(seeds, k * seeds)
        others.append({m: mean_rmse(m, more) for m in ("spsa_stereo", "ekf", "triangulation")})
    md += ["", summary(table, others, seeds), "", "## The outlier gate", "",
           "Per method over the *5 % outliers* runs: the injected outliers its gate rejected; over the *clean* runs: "
           "the clean camera observations it rejected; restarts (a camera gated 8 frames in a row) over all runs. "
           "Methods without a gate are left out.", "",
           "| method | outliers rejected | clean observations rejected | restarts |", "|---|---:|---:|---:|"]
    for m, (rej, inj, false, seen, restarts) in gating.items():
        if rej or false or restarts:
            md.append(f"| {m} | {rej} of {inj} ({100 * rej / inj:.1f} %) | {false} of {seen} ({100 * false / seen:.2f} %) "
                      f"| {restarts} |")
    write_text(out_dir / "trackers.md", "\n".join(md) + "\n")
    print(f"\nwrote {out_dir / 'trackers.md'}")


def count_gating(acc: list[int], cond: str, tr, bad: np.ndarray | None) -> None:
    """Add one run's gate counts to ``acc`` (see the gate table of :func:`simulated_suite`)."""
    gated = np.nan_to_num(tr.extra.get("gated", np.zeros(len(tr.position))))
    acc[4] += int(np.nansum(tr.extra.get("restart", [0])))
    if cond == "outliers" and bad is not None:
        acc[0] += int(np.minimum(gated[bad], 1).sum())  # one bad camera per bad frame
        acc[1] += int(bad.sum())
    elif cond == "clean":
        acc[2] += int(gated.sum())
        acc[3] += 2 * len(gated)


def ratios(table: dict[str, dict[str, float]]) -> tuple[list[float], list[float]]:
    """Per condition: spsa_stereo's RMSE over the EKF's, and triangulation's over spsa_stereo's."""
    return ([table["spsa_stereo"][c] / table["ekf"][c] for c in CONDITIONS],
            [table["triangulation"][c] / table["spsa_stereo"][c] for c in CONDITIONS])


def summary(table: dict[str, dict[str, float]], others: list[dict[str, dict[str, float]]], seeds: int) -> str:
    """The sentences the docs quote, computed from the table (seeds 0 … seeds − 1) and from the
    same methods on the other seed sets: spsa_stereo against the EKF and triangulation per condition."""
    ekf, tri = ratios(table)
    worst = CONDITIONS[int(np.argmax(ekf))]
    text = (f"On seeds 0–{seeds - 1} (the table), spsa_stereo's RMSE is {min(ekf):.2f}–{max(ekf):.2f}× the EKF's "
            f"across the nine conditions (largest: {CONDITION_TEXT[worst]}), and triangulation's is "
            f"{min(tri):.2f}–{max(tri):.2f}× spsa_stereo's.")
    if not others:
        return text
    all_ekf = [r for t in [table, *others] for r in ratios(t)[0]]
    all_tri = [r for t in [table, *others] for r in ratios(t)[1]]
    return (text + f" Over {len(others) + 1} disjoint seed sets of {seeds} seeds (seeds 0–{(len(others) + 1) * seeds - 1}) "
            f"the first ratio spans {min(all_ekf):.2f}–{max(all_ekf):.2f}× and the second {min(all_tri):.2f}–"
            f"{max(all_tri):.2f}×.")


#: The imperfect-rig suite (data/scenarios/), each rendered, detected and estimated end to end.
IMPERFECT = ("rig_left", "rig_above", "rig_below", "rig_diagonal", "rig_from_file", "distortion", "sync_offset",
             "rolling_shutter", "exposure_blur", "drops_jitter", "calibration_error", "occlusion", "lookalike",
             "realistic")


def imperfect_suite(frames: int, out_dir) -> None:
    """Every point method on rendered clips of the imperfect-rig suite, through the pipeline itself:
    the blob detector on the frames, each method from the shared initiator at its defaults, and the
    same two-marker scene on an ideal rig as the reference column. Cells are 3-D RMSE in mm over
    both markers (per-clip pooled); * marks a method more than 5× triangulation's RMSE there."""
    import tempfile
    import warnings

    from detectors.stage import detect_clip
    from pipeline.estimate import estimate_clip
    from renderers.render import render_clip

    ideal = load_scenario("sync_offset").model_dump(mode="json")
    ideal["rig"]["sync_offset_s"] = 0.0
    scens = {"ideal": parse_scenario({**ideal, "name": "ideal", "frames": frames})}
    scens.update({n: load_scenario(n).with_overrides(frames=frames) for n in IMPERFECT})
    names = [m for m in methods("point")]
    rmse: dict[str, dict[str, float | None]] = {}
    md = LiveDoc(["# Trackers on the imperfect-rig suite", "",
                  f"Generated by `python benchmarks/trackers.py --suite imperfect --imperfect-frames {frames}`: each "
                  f"scenario of the suite rendered ({frames} frames, 640×480, lossless PNG), the blob detector on the "
                  "frames, every point method from the shared initiator at its defaults (no truth given to any); "
                  "cells are 3-D RMSE in mm over both markers, * where a method is more than 5× triangulation's "
                  "RMSE on that clip. *ideal* is the same two-marker scene on an ideal rig.", "",
                  "| scenario | " + " | ".join(names) + " |", "|---|" + "---:|" * len(names)])
    with tempfile.TemporaryDirectory() as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for n, scen in scens.items():
            clip = f"{tmp}/{n}"
            render_clip(scen, clip, fmt="png", workers=2)
            detect_clip(clip)
            res = estimate_clip(clip, RunSettings(methods=names))
            rmse[n] = {m: res.metrics["methods"][m].get("rmse") for m in names}
            tri = rmse[n]["triangulation"] or float("inf")
            cells = ["—" if v is None else f"{1000 * v:.1f}{'*' if v > 5 * tri else ''}" for v in rmse[n].values()]
            md.append(f"| {n} | " + " | ".join(cells) + " |")
    write_text(out_dir / "trackers_imperfect.md", "\n".join(md) + "\n")
    print(f"\nwrote {out_dir / 'trackers_imperfect.md'}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--seed-sets", type=int, default=3, help="disjoint seed sets for the summary sentence's spread")
    ap.add_argument("--suite", choices=("simulated", "imperfect", "all"), default="all",
                    help="the simulated conditions, the rendered imperfect-rig suite, or both")
    ap.add_argument("--imperfect-frames", type=int, default=90)
    add_output_args(ap)
    args = ap.parse_args()
    out_dir = output_dir(args, "trackers")
    if args.suite in ("simulated", "all"):
        simulated_suite(args.seeds, out_dir, args.seed_sets)
    if args.suite in ("imperfect", "all"):
        imperfect_suite(args.imperfect_frames, out_dir)


if __name__ == "__main__":
    main()
