"""Reproduce the thesis's claims and the lecture's alpha-beta figures on
simulated observations; writes thesis.md and figures/ to --out (a temporary folder by default; docs/
with --write-docs), printing each row as it is measured.

    python benchmarks/thesis.py [--seeds 10] [--seed-sets 3] [--out DIR | --write-docs]

Settings (the thesis gives no units; ours): the `receding` and `maneuvering` built-in scenarios
(640×480, f = 600 px, baseline 0.3 m, 2° toe-in, 30 fps, the point receding from 1.5 m to 7.5 m
over 300 frames); image noise σ_img in pixels on every coordinate. Starts are given: the true
velocity and the true position plus N(0, σ_start²) per axis — σ_start = 5 cm in (b)–(f) (10–20×
closer than the thesis), and the thesis's own pairs (σ_img, σ_start) = (0.02, 0.5) and (0.1, 1.0),
read as pixels and metres, in their own section. Every table has the predict-only row (the same
start, no update). EKF "correct covariances": R = σ_img² I, q = 1e-4 m²/s³ (the motion is
constant-velocity); "wrong": q × 100 and R × 0.01, and the reverse. Algorithm 1 and the 2009 SPSA
run at their defaults (α = 0.1, β = 0.01, th = 0.03; the 2009 algorithm without the projection
rule, as published).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from _common import LiveDoc, add_output_args, output_dir

from pipeline.core.alphabeta import ABFilter
from pipeline.core.camera import triangulate
from pipeline.core.io import atomic_path, write_text
from pipeline.estimators import Estimator, create
from renderers.motion import simulate_truth
from renderers.scenario import load_scenario

THESIS_R1 = {1000: (0.621511, 0.030874), 3000: (1.909988, 0.128089), 5000: (3.213213, 0.267196)}
LECTURE_R4 = {"uniform": (0.070, None), "accelerated": (0.072, 0.042), "sinusoid": (0.144, 0.132)}


def setup(name: str, frames: int = 300):
    s = load_scenario(name).with_overrides(frames=frames)
    tr = simulate_truth(s)
    return s.rig.build(), s.dt, tr.positions[:, 0], tr.velocities[:, 0]


#: (b) noise-free; (c)–(e) σ_img = 2 px; (f) `maneuvering`, σ_img = 1 px: the methods and their settings
B_CFGS = {"spsa": ("spsa", {}), "spsa_vgg": ("spsa_vgg", {}), "spsa_stereo": ("spsa_stereo", {}),
          "predict_only": ("predict_only", {}), "predict_only (static)": ("predict_only", {})}
S_IMG_C = 2.0
_GOOD = {"pixel_sigma": S_IMG_C, "process_noise": 1e-4}
C_CFGS = {
    "spsa": ("spsa", {}), "spsa, no projection rule": ("spsa", {"th": 1e12}),
    "ekf, correct covariances": ("ekf", _GOOD),
    "ekf, q×100, R×0.01": ("ekf", {**_GOOD, "q_scale": 100.0, "r_scale": 0.01}),
    "ekf, q×0.01, R×100": ("ekf", {**_GOOD, "q_scale": 0.01, "r_scale": 100.0}),
    "spsa_stereo": ("spsa_stereo", {}),
    "triangulation": ("triangulation", {}),
    "predict_only": ("predict_only", {}),
}
F_CFGS = {"spsa": ("spsa", {}), "spsa, th = 0.003 (earlier default)": ("spsa", {"th": 0.003}),
          "spsa, no projection": ("spsa", {"th": None}), "spsa_stereo": ("spsa_stereo", {}),
          "ekf (q = 1)": ("ekf", {"pixel_sigma": 1.0, "process_noise": 1.0}), "triangulation": ("triangulation", {}),
          "predict_only": ("predict_only", {})}


def headlines(first_seed: int, seeds: int) -> dict[str, tuple[float, bool]]:
    """The figures the sentences of (b)–(f) quote, and each claim's verdict, on the seeds
    ``first_seed`` … ``first_seed + seeds − 1``: (label → (value, supported))."""
    rig, dt, X, V = setup("receding")
    fb = {k: final(v) for k, v in run_methods(rig, dt, X, V, 0.0, seeds, B_CFGS, first_seed=first_seed).items()}
    c = run_methods(rig, dt, X, V, S_IMG_C, seeds, C_CFGS, first_seed=first_seed)
    r, fin = {k: rmse(v) for k, v in c.items()}, {k: final(v) for k, v in c.items()}
    rig_m, dt_m, Xm, Vm = setup("maneuvering")
    rf = {k: rmse(v) for k, v in run_methods(rig_m, dt_m, Xm, Vm, 1.0, seeds, F_CFGS, first_seed=first_seed).items()}
    return {
        "(b) 2009 SPSA final error ÷ start held (latches: > 0.5)": (fb["spsa_vgg"] / fb["predict_only (static)"],
                                                                   fb["spsa_vgg"] > 0.5 * fb["predict_only (static)"]),
        "(b) 2009 SPSA ÷ Algorithm 1, final error (follows: > 2)": (fb["spsa_vgg"] / fb["spsa"],
                                                                   fb["spsa"] < 0.5 * fb["spsa_vgg"]),
        "(c) no projection rule ÷ with it, final error (> 2)": (fin["spsa, no projection rule"] / fin["spsa"],
                                                               fin["spsa, no projection rule"] > 2 * fin["spsa"]),
        "(d) Algorithm 1 ÷ EKF (correct), RMSE (> 1)": (r["spsa"] / r["ekf, correct covariances"],
                                                       r["ekf, correct covariances"] < r["spsa"]),
        "(e) EKF (q×100, R×0.01) ÷ Algorithm 1, RMSE (> 1)": (r["ekf, q×100, R×0.01"] / r["spsa"],
                                                             r["ekf, q×100, R×0.01"] > r["spsa"]),
        "(f) Algorithm 1 RMSE, m (below predict-only and triangulation)": (
            rf["spsa"], rf["spsa"] < rf["predict_only"] and rf["spsa"] < rf["triangulation"]),
        "(f) Algorithm 1 without projection, RMSE, m (runs away: > 10× with it)": (
            rf["spsa, no projection"], rf["spsa, no projection"] > 10 * rf["spsa"]),
        "(f) spsa_stereo RMSE, m (below Algorithm 1)": (rf["spsa_stereo"], rf["spsa_stereo"] < rf["spsa"]),
    }


def across(runs: list[dict[str, tuple[float, bool]]], label: str) -> str:
    """A headline's spread for its sentence: on how many seed sets the claim holds, the figure's
    median and range over them."""
    vals = np.array([r[label][0] for r in runs])
    holds = sum(r[label][1] for r in runs)
    return (f" [over {len(runs)} seed sets: holds on {holds} of {len(runs)}; figure median {np.median(vals):.3g}, "
            f"range {vals.min():.3g}–{vals.max():.3g}]")


def spread(runs: list[dict[str, tuple[float, bool]]], seeds: int) -> list[str]:
    """The last section: each headline figure and verdict on the disjoint seed sets of ``runs``
    (the first is the one the sentences above quote)."""
    sets = len(runs)
    cols = [f"seeds {k * seeds}–{(k + 1) * seeds - 1}" for k in range(sets)]
    rows = ["## Spread over seed sets", "",
            f"The sentences above quote one seed set (seeds 0–{seeds - 1}). Each figure they rest on, on {sets} "
            f"disjoint sets of {seeds} seeds, with the median and range over the sets and on how many sets the "
            "claim holds:", "",
            "| figure (claim) | " + " | ".join(cols) + " | median | range | claim holds |",
            "|---|" + "---|" * (len(cols) + 3)]
    for label in runs[0]:
        vals = np.array([r[label][0] for r in runs])
        holds = sum(r[label][1] for r in runs)
        rows.append(f"| {label} | " + " | ".join(f"{v:.3g}" for v in vals)
                    + f" | {np.median(vals):.3g} | {vals.min():.3g}–{vals.max():.3g} | {holds} of {sets} |")
    return [*rows, "", "A claim that holds on some sets and not others rests on seed luck; a ratio whose range spans "
            "orders of magnitude (a runaway's error) says only that it runs away.", ""]


def verdict(ok: bool) -> str:
    return "**Supported**" if ok else "**Not supported**"


def given(X, V, rng, sigma_start=0.05):
    return {"mode": "given", "state": tuple(np.r_[X[0] + rng.normal(0, sigma_start, 3), V[0]].tolist()),
            "sigma_position": sigma_start, "sigma_velocity": 0.05}


def err(P, X):
    return np.linalg.norm(P - X, axis=1)


def run_methods(rig, dt, X, V, sigma, seeds, cfgs, sigma_start=0.05, first_seed=0):
    """method key → list over seeds (``first_seed`` on) of per-frame error arrays."""
    out: dict[str, list[np.ndarray]] = {k: [] for k in cfgs}
    for seed in range(first_seed, first_seed + seeds):
        rng = np.random.default_rng(seed)
        Y = rig.project(X) + rng.normal(0, sigma, (len(X), 4))
        init = given(X, V, rng, sigma_start)
        for key, (m, cfg) in cfgs.items():
            c = {**cfg, "seed": seed}
            if m != "triangulation":
                c["init"] = {**init, **cfg.get("init", {})}
            if m == "predict_only" and key.endswith("(static)"):
                c["static"] = True
            out[key].append(err(create(m, rig, dt, c).run(Y).position, X))
    return out


def rmse(errs):
    return float(np.mean([np.sqrt(np.nanmean(e**2)) for e in errs]))


def band(errs, sel):
    """RMSE over the frames ``sel`` (a depth band), mean over seeds."""
    return float(np.mean([np.sqrt(np.mean(e[sel] ** 2)) for e in errs]))


def final(errs):
    return float(np.mean([e[-1] for e in errs]))


def save(fig, path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100, bbox_inches="tight")
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--seed-sets", type=int, default=3, help="disjoint seed sets for the headline figures' spread")
    add_output_args(ap)
    args = ap.parse_args()
    args.out = output_dir(args, "thesis")
    figs = args.out / "figures"
    md = LiveDoc(["# The thesis reproduced (Krivokon 2011)", "",
          f"Generated by `python benchmarks/thesis.py --seeds {args.seeds} --seed-sets {args.seed_sets}` — settings "
          f"in its docstring. {args.seeds} seeds per cell (seeds 0–{args.seeds - 1}, one seed set); numbers are means "
          f"over seeds. The last section gives every headline figure over {args.seed_sets} disjoint seed sets.", ""])
    rig, dt, X, V = setup("receding")
    runs = [headlines(k * args.seeds, args.seeds) for k in range(args.seed_sets)]  # runs[0]: the seeds quoted below
    H = list(runs[0])  # the headline labels, in order: (b) ×2, (c), (d), (e), (f) ×3

    # (a) triangulation error vs image noise (thesis Fig. 2)
    sig = [0.25, 0.5, 1.0, 2.0, 4.0]
    tri = {s: [err(triangulate(rig, rig.project(X) + np.random.default_rng(k).normal(0, s, (len(X), 4))), X)
               for k in range(args.seeds)] for s in sig}
    md += ["## (a) Triangulation error grows with image noise (and with depth)", "",
           "| σ_img (px) | " + " | ".join(f"{s:g}" for s in sig) + " |", "|---|" + "---|" * len(sig),
           "| 3-D RMSE (m) | " + " | ".join(f"{rmse(tri[s]):.3f}" for s in sig) + " |",
           "| error at 1.5–3 m (m) | " + " | ".join(f"{band(tri[s], X[:, 2] < 3):.3f}" for s in sig) + " |",
           "| error at 6–7.5 m (m) | " + " | ".join(f"{band(tri[s], X[:, 2] > 6):.3f}" for s in sig) + " |",
           "", "**Supported**: the error grows roughly linearly with σ_img and with depth (∝ z²/baseline).", "",
           "![triangulation](figures/thesis_a_triangulation.png)", ""]
    fig, ax = plt.subplots(figsize=(7, 4))
    for s in sig:
        ax.semilogy(X[:, 2], np.mean(tri[s], axis=0), label=f"σ = {s:g} px")
    ax.set(xlabel="depth z (m)", ylabel="triangulation error (m)", title="(a) triangulation error vs depth and noise")
    ax.legend()
    ax.grid(alpha=0.3, which="both")
    save(fig, figs / "thesis_a_triangulation.png")

    # (b) noise-free: unmodified SPSA latches, Algorithm 1 follows
    b = run_methods(rig, dt, X, V, 0.0, args.seeds, B_CFGS)
    md += ["## (b) Noise-free: the unmodified SPSA latches, Algorithm 1 follows", "",
           "| method | 3-D RMSE (m) | final error (m) |", "|---|---|---|"]
    md += [f"| {k} | {rmse(v):.3f} | {final(v):.3f} |" for k, v in b.items()]
    fb = {k: final(v) for k, v in b.items()}
    latches = fb["spsa_vgg"] > 0.5 * fb["predict_only (static)"]
    md += ["", "`predict_only` is Algorithm 1's baseline (the true velocity carried forward); `predict_only "
           "(static)` the 2009 algorithm's (the start held).", "",
           f"- The unmodified SPSA latches: {verdict(latches)} — final error {fb['spsa_vgg']:.2f} m against "
           f"{fb['predict_only (static)']:.2f} m for holding the start{across(runs, H[0])}.",
           f"- Algorithm 1 follows: {verdict(fb['spsa'] < 0.5 * fb['spsa_vgg'])} relative to the 2009 SPSA "
           f"({fb['spsa']:.3f} m final, {fb['spsa_vgg'] / fb['spsa']:.1f}× lower{across(runs, H[1])}) — but the "
           "following is its "
           f"prediction's: with the true velocity given and no noise, predict-only is exact "
           f"({fb['predict_only']:.3f} m, the start error), and Algorithm 1's update "
           + ("improves on it." if fb["spsa"] < fb["predict_only"] else "only adds error to it.")
           + f" `spsa_stereo`: {fb['spsa_stereo']:.3f} m.", "",
           "![latching](figures/thesis_b_latching.png)", ""]
    fig, ax = plt.subplots(figsize=(7, 4))
    for k, lab in (("spsa", "Algorithm 1"), ("predict_only", "true velocity carried (Algorithm 1's baseline)"),
                   ("spsa_vgg", "unmodified SPSA (2009)"), ("predict_only (static)", "start held (2009 baseline)"),
                   ("spsa_stereo", "spsa_stereo")):
        ax.plot(np.mean(b[k], axis=0), label=lab)
    ax.set(xlabel="frame", ylabel="3-D error (m)", title="(b) noise-free tracking")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    save(fig, figs / "thesis_b_latching.png")

    # (c)–(e) with image noise
    s_img = S_IMG_C
    c = run_methods(rig, dt, X, V, s_img, args.seeds, C_CFGS)
    md += [f"## (c)–(e) With image noise (σ_img = {s_img:g} px, σ_start = 5 cm)", "",
           "| method | 3-D RMSE (m) | final error (m) | worst error (m) |", "|---|---|---|---|"]
    for k, v in c.items():
        md.append(f"| {k} | {rmse(v):.3f} | {final(v):.3f} | {np.mean([np.nanmax(e) for e in v]):.3f} |")
    r = {k: rmse(v) for k, v in c.items()}
    fin = {k: final(v) for k, v in c.items()}
    md += ["",
           f"- **(c)** {verdict(fin['spsa, no projection rule'] > 2 * fin['spsa'])}: without the projection rule "
           f"the final error is {fin['spsa, no projection rule'] / fin['spsa']:.3g}× larger{across(runs, H[2])}; with "
           "it the estimate stays "
           f"bounded ({fin['spsa']:.3f} m final) — but it is worse than its predict-only baseline "
           f"({fin['predict_only']:.3f} m, the true velocity carried forward) and than triangulation "
           f"({r['triangulation']:.3f} m RMSE against {r['spsa']:.3f} m)."
           if fin["spsa"] > fin["predict_only"] else
           f"- **(c)** {verdict(fin['spsa, no projection rule'] > 2 * fin['spsa'])}: without the projection rule the "
           f"final error is {fin['spsa, no projection rule'] / fin['spsa']:.3g}× larger{across(runs, H[2])}; with it, "
           f"{fin['spsa']:.3f} m (predict-only {fin['predict_only']:.3f} m).",
           f"- **(d)** {verdict(r['ekf, correct covariances'] < r['spsa'])}: the EKF with correct covariances has "
           f"{r['spsa'] / r['ekf, correct covariances']:.1f}× lower RMSE than Algorithm 1{across(runs, H[3])}.",
           f"- **(e)** {verdict(r['ekf, q×100, R×0.01'] > r['spsa'])} for Algorithm 1: with q×100 and R×0.01 the EKF "
           f"has {r['ekf, q×100, R×0.01']:.3f} m RMSE against Algorithm 1's {r['spsa']:.3f} m{across(runs, H[4])}; "
           "with q×0.01 and R×100 "
           f"{r['ekf, q×0.01, R×100']:.3f} m (on a constant-velocity track that error agrees with the true dynamics). "
           f"`spsa_stereo`, which needs no noise statistics either, has {r['spsa_stereo']:.3f} m.",
           "", "![noise](figures/thesis_cde.png)", ""]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for k, v in c.items():
        ax.semilogy(np.mean(v, axis=0), label=k)
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set(xlabel="frame", ylabel="3-D error (m)", title=f"(c)–(e) σ_img = {s_img:g} px")
    ax.grid(alpha=0.3, which="both")
    save(fig, figs / "thesis_cde.png")

    # (f) maneuvering
    rig_m, dt_m, Xm, Vm = setup("maneuvering")
    f = run_methods(rig_m, dt_m, Xm, Vm, 1.0, args.seeds, F_CFGS)
    md += ["## (f) Curved trajectories (process noise: `maneuvering`, σ_img = 1 px)", "",
           "| method | 3-D RMSE (m) | final error (m) |", "|---|---|---|"]
    md += [f"| {k} | {rmse(v):.3f} | {final(v):.3f} |" for k, v in f.items()]
    rf = {k: rmse(v) for k, v in f.items()}
    md += ["", f"{verdict(rf['spsa'] < rf['predict_only'] and rf['spsa'] < rf['triangulation'])} in the sense that "
           f"matters{across(runs, H[5])}: Algorithm 1 ({rf['spsa']:.3f} m) "
           + ("beats" if rf["spsa"] < rf["predict_only"] else "does not beat")
           + f" its predict-only baseline ({rf['predict_only']:.3f} m) and "
           + ("beats" if rf["spsa"] < rf["triangulation"] else "does not beat")
           + f" triangulation ({rf['triangulation']:.3f} m). It adapts to direction changes only partly: the "
           "projection rule that bounds it also caps how fast it turns, and without the rule it "
           + ("runs away" if rf["spsa, no projection"] > 10 * rf["spsa"] else "is no better")
           + f" ({rf['spsa, no projection']:.3g} m{across(runs, H[6])}). `spsa_stereo` has {rf['spsa_stereo']:.3f} m"
           f"{across(runs, H[7])} and the EKF with a "
           f"matching process noise {rf['ekf (q = 1)']:.3f} m.", ""]

    # the thesis's own settings
    md += ["## The thesis's own settings (σ_img, σ_start) = (0.02, 0.5) and (0.1, 1.0)", "",
           "Read as pixels and metres (the thesis states neither); `receding`; start = true velocity and the "
           "true position plus N(0, σ_start²) per axis, the same for every method.", "",
           "| σ_img (px) | σ_start (m) | method | 3-D RMSE (m) | final error (m) |", "|---|---|---|---|---|"]
    notes: list[str] = []
    for s_img_t, s_start in ((0.02, 0.5), (0.1, 1.0)):
        th = run_methods(rig, dt, X, V, s_img_t, args.seeds, {
            "spsa": ("spsa", {}), "spsa, no projection": ("spsa", {"th": None}), "spsa_vgg": ("spsa_vgg", {}),
            "spsa_stereo": ("spsa_stereo", {}),
            "ekf, correct covariances": ("ekf", {"pixel_sigma": s_img_t, "process_noise": 1e-4,
                                                 "init": {"sigma_position": s_start}}),
            "triangulation": ("triangulation", {}), "predict_only": ("predict_only", {})}, sigma_start=s_start)
        md += [f"| {s_img_t:g} | {s_start:g} | {k} | {rmse(v):.3f} | {final(v):.3f} |" for k, v in th.items()]
        rt = {k: rmse(v) for k, v in th.items()}
        notes.append(f"- σ_img {s_img_t:g}, σ_start {s_start:g}: Algorithm 1 {rt['spsa']:.3f} m against predict-only "
                     f"{rt['predict_only']:.3f} m ({'better' if rt['spsa'] < rt['predict_only'] else 'not better'}), "
                     f"triangulation {rt['triangulation']:.3f} m, `spsa_stereo` {rt['spsa_stereo']:.3f} m, EKF "
                     f"{rt['ekf, correct covariances']:.3f} m.")
    md += ["", *notes, ""]

    # why Algorithm 1 stalls on this rig, and what spsa_stereo does instead
    H = [np.linalg.eigvalsh(J.T @ J) for J in rig.jacobian(X[[0, -1]])]
    z0, z1 = (float(z) for z in rig.left.depth(X[[0, -1]]))
    md += ["## `spsa_stereo`: why Algorithm 1 stalls on a stereo rig, and what tracks", "",
           f"The reprojection cost's curvature in metres (eigenvalues of JᵀJ) on `receding`'s rig ({rig.baseline:g} m "
           f"baseline) is {H[0][-1] / H[0][0]:.0f}× weaker along its flattest direction (depth) than along its "
           f"steepest at z = {z0:.1f} m, and {H[1][-1] / H[1][0]:.0f}× at z = {z1:.1f} m: a gain small enough to be "
           "stable sideways leaves depth, and the velocity learned from it, practically unchanged — what (c) and the "
           "thesis-settings table show. `spsa_stereo` keeps Algorithm 1's ingredients (simultaneous ±1 "
           "perturbations, a linear prediction, no noise statistics, no matrix inversion) and changes three things:",
           "",
           "1. it minimises *each frame's* cost at the predicted position, not a cost pairing two frames;",
           "2. in the coordinates q = (x/z, y/z, x/z − b/z) — the left image point and the right camera's x — where "
           f"the cost's Hessian is 2·diag(1, 2, 1) for a rectified rig at any depth (curvature ratio 2, not "
           f"{H[0][-1] / H[0][0]:.0f}–{H[1][-1] / H[1][0]:.0f}): "
           "one simultaneous-perturbation Newton step over the four cube diagonals (nine cost evaluations, a scalar "
           "curvature) lands on the frame's minimum;",
           "3. it corrects image coordinates and disparity with growing-memory line-fit gains that fall to a floor, "
           "each with its own memory, shortened by Kesten's rule when the innovations keep one sign; the velocity "
           "comes from the position corrections.", "",
           "The equations are in `pipeline/estimators/spsa_stereo.py`; its accuracy, divergence rate and speed "
           "against every point method on the scenario suite are in [trackers.md](trackers.md) "
           "(`python benchmarks/trackers.py`). In the thesis-settings table above triangulation is the one to beat: "
           "with 0.02 or 0.1 px of image noise it is within millimetres or centimetres from the first frame, while "
           "every filter there starts 0.5 or 1 m off and carries that error for some frames.", ""]

    # R1 timing
    md += ["## R1 — time to filter one trajectory (seconds)", "",
           "Both methods two ways, measured in the same run (best of 3): *interpreted* is `Estimator.run`, a "
           "per-frame Python loop (Algorithm 1 in Python floats, the EKF's matrices in numpy); *compiled* is `run` "
           "itself, the numba cores tested equal to the interpreted loops to 1e-9.", "",
           "| iterations | thesis KF | thesis Alg. 1 | thesis ratio | EKF interpreted | Alg. 1 interpreted | ratio "
           "| EKF compiled | Alg. 1 compiled | ratio |", "|---|---|---|---|---|---|---|---|---|---|"]
    r1 = []
    for n, (tk, ta) in THESIS_R1.items():
        rig_t, dt_t, Xt, _ = setup("receding", n)
        Yt = rig_t.project(Xt) + np.random.default_rng(0).normal(0, 1.0, (n, 4))
        t = {(m, way): min(_timed(lambda m=m, f=f, r=rig_t, d=dt_t, y=Yt: f(create(m, r, d), y)) for _ in range(3))
             for m in ("ekf", "spsa") for way, f in (("py", Estimator.run), ("jit", lambda e, y: e.run(y)))}
        r1.append((t["ekf", "py"] / t["spsa", "py"], t["ekf", "jit"] / t["spsa", "jit"]))
        md.append(f"| {n} | {tk:.3f} | {ta:.3f} | {tk / ta:.0f}× | {t['ekf', 'py']:.3f} | {t['spsa', 'py']:.4f} | "
                  f"{r1[-1][0]:.1f}× | {t['ekf', 'jit']:.4f} | {t['spsa', 'jit']:.5f} | {r1[-1][1]:.1f}× |")
    lo_py, hi_py = min(r[0] for r in r1), max(r[0] for r in r1)
    lo_c, hi_c = min(r[1] for r in r1), max(r[1] for r in r1)
    md += ["", f"Interpreted, Algorithm 1 is {lo_py:.1f}–{hi_py:.1f}× faster than the EKF; compiled, {lo_c:.1f}–{hi_c:.1f}×; "
           "the thesis reports 12–20×. Compiled, a method's time per frame is its arithmetic: an EKF step (prediction, a "
           "4 × 4 inverse and the Joseph update, about a thousand multiply-adds) against Algorithm 1's two cost "
           f"evaluations and a six-vector update. That advantage is real, and {lo_c:.1f}–{hi_c:.1f}× here. Interpreted, each "
           "step also pays the per-frame overhead of the loop around it (here one `Step` object per frame for both "
           "methods), which narrows or widens the gap with how the loops are written, not with the algorithms. The "
           "thesis's 12–20× therefore describes its implementations (the paper does not say how its Kalman filter was "
           "coded) more than the methods: on equal footing, interpreted or compiled, we measure no more than "
           f"{max(hi_py, hi_c):.1f}×.", ""]

    # R4 alpha-beta(-gamma)
    md += ["## R4 — alpha-beta and alpha-beta-gamma (lecture 002)", "",
           "1-D, unit time steps, 100 samples, Gaussian measurement noise σ = 0.243 (MAE ≈ 0.194 as in the "
           "lecture); gains (the lecture gives none) α = 0.2 with Benedict–Bordner β = α²/(2 − α) = 0.022, "
           "γ = β²/(2α) = 0.0012. Uniform: x = 0.1 t; accelerated: x = 0.002 t²; sinusoid: x = sin(2π t / 100). "
           "MAE after a 10-sample settling. Ratios to the measurement MAE compare shapes.", "",
           "| motion | measurement MAE | αβ MAE (lecture) | αβγ MAE (lecture) | αβ/meas. ours (lecture) | "
           "αβγ/meas. ours (lecture) |", "|---|---|---|---|---|---|"]
    r4: dict[str, tuple[float, float]] = {}
    for motion, (l_ab, l_abg) in LECTURE_R4.items():
        m_meas, m_ab, m_abg = _r4(motion, args.seeds)
        r4[motion] = (m_ab, m_abg)
        labg = f"{l_abg:.3f}" if l_abg else "—"
        rabg = f"{l_abg / 0.194:.2f}" if l_abg else "—"
        md.append(f"| {motion} | {m_meas:.3f} (0.194) | {m_ab:.3f} ({l_ab:.3f}) | {m_abg:.3f} ({labg}) | "
                  f"{m_ab / m_meas:.2f} ({l_ab / 0.194:.2f}) | {m_abg / m_meas:.2f} ({rabg}) |")
    md += ["", "Agrees with the lecture where it matters: filtering removes most of the noise on smooth motion and "
           "the gamma term pays off under constant acceleration (the alpha-beta filter lags there). On our sinusoid "
           "the gamma term does not help (the lecture reports 0.132 vs 0.144); its gains and trajectory are not "
           "given, and on a sinusoid the acceleration is never constant, so the extra state mostly adds noise.", "",
           "The γ convention: our αβγ (like filterpy's `GHKFilter`) adds 2γ·r/dt² to the acceleration, the lecture's "
           "formula γ·r/dt², so the same γ means twice the acceleration correction here. The cells off the "
           f"lecture are the accelerated ones: αβ {r4['accelerated'][0] / LECTURE_R4['accelerated'][0]:.1f}× and αβγ "
           f"{r4['accelerated'][1] / LECTURE_R4['accelerated'][1]:.1f}× the lecture's MAE. With the lecture's gains "
           "unknown (its gains may well be larger, which an accelerating target favours) we compare shapes: the "
           "ordering αβγ < αβ under acceleration " + ("holds" if r4["accelerated"][1] < r4["accelerated"][0]
                                                     else "does not hold") + " here, the absolute values do not.", ""]
    md += spread(runs, args.seeds)
    out = args.out / "thesis.md"
    write_text(out, "\n".join(md) + "\n")
    print(f"\nwrote {out}")


def _timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def _r4(motion: str, seeds: int) -> tuple[float, float, float]:
    t = np.arange(100, dtype=float)
    x = {"uniform": 0.1 * t, "accelerated": 0.002 * t * t, "sinusoid": np.sin(2 * np.pi * t / 100)}[motion]
    a = 0.2
    b = a * a / (2 - a)
    g = b * b / (2 * a)
    meas, ab, abg = [], [], []
    for s in range(seeds):
        z = x + np.random.default_rng(s).normal(0, 0.243, len(t))
        f1, f2 = ABFilter(z[:1], 1.0, a, b), ABFilter(z[:1], 1.0, a, b, g)
        e1, e2 = [z[0]], [z[0]]
        for zk in z[1:]:
            f1.predict()
            f1.correct(np.array([zk]))
            f2.predict()
            f2.correct(np.array([zk]))
            e1.append(f1.x[0])
            e2.append(f2.x[0])
        meas.append(np.mean(np.abs(z - x)))
        ab.append(np.mean(np.abs(np.array(e1) - x)[10:]))
        abg.append(np.mean(np.abs(np.array(e2) - x)[10:]))
    return float(np.mean(meas)), float(np.mean(ab)), float(np.mean(abg))


if __name__ == "__main__":
    main()
