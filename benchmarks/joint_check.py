"""The joint check of the cameras kept over three cameras or more, on rendered rings: the EKF and kf3d
with the check (a failed check drops the camera the others agree without, :class:`ViewCheck`),
with the previous rule (drop the camera of largest own NIS) and without the check, as `run` gives
them (σ estimated from the detections).

    python benchmarks/joint_check.py [--frames 90] [--write-docs]

"Chosen on": the ring scenario's three markers on eight rings (3–6 cameras, one with the cameras 12,
−8 and 20 ms apart, aligned by its timestamps) — the renders the rule was chosen on. "Held out":
four rings written before they were measured, the markers' motions changed (sinusoids 1.3× faster
and 0.9 rad later, the straight mover 1.5× faster).
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
from pathlib import Path

import numpy as np
from _common import page

from detectors.stage import detect_clip
from pipeline.core.clip import Clip
from pipeline.core.settings import RunSettings
from pipeline.estimate import observe
from pipeline.estimators import create
from renderers.render import render_clip
from renderers.scenario import Scenario, load_scenario, parse_scenario

#: name → (cameras, radius m, height m (negative: above the volume), fps, seed, camera offsets s, held out)
RINGS = {
    "ring4": (4, 2.0, -0.8, 30, 0, None, False),
    "ring4, timestamps": (4, 2.0, -0.8, 30, 0, (0.0, 0.012, -0.008, 0.02), False),
    "ring3": (3, 2.0, -0.8, 30, 1, None, False),
    "ring3, 60 fps": (3, 2.5, -1.2, 60, 2, None, False),
    "ring5": (5, 2.0, -0.8, 30, 3, None, False),
    "ring5, below": (5, 3.0, 0.5, 30, 4, None, False),
    "ring6, 60 fps": (6, 2.5, -0.5, 60, 5, None, False),
    "ring4, 60 fps": (4, 2.5, -1.5, 60, 6, None, False),
    "ring4 (held out)": (4, 1.8, -0.6, 30, 7, None, True),
    "ring5, 60 fps (held out)": (5, 2.2, -1.0, 60, 8, None, True),
    "ring3, below (held out)": (3, 2.2, 0.4, 30, 9, None, True),
    "ring6 (held out)": (6, 3.0, -1.3, 30, 10, None, True),
}
RULES = ("with the check", "previous rule", "without")


def scenario(cameras: int, radius: float, height: float, fps: int, seed: int, offsets, held_out: bool,
             frames: int) -> Scenario:
    """The ring scenario on another ring (held out: the markers' motions changed too)."""
    data = load_scenario("ring").model_dump(mode="json")
    data["rig"]["ring"] = {"cameras": cameras, "radius": radius, "height": height}
    data["rig"].pop("views")  # made from the ring
    if held_out:
        for obj in data["objects"]:
            m = obj["motion"]
            if m["type"] == "sinusoid":
                m["frequency_hz"] = [1.3 * f for f in m["frequency_hz"]]
                m["phase"] = [p + 0.9 for p in (m.get("phase") or [0.0] * 3)]
            else:
                m["velocity"] = [1.5 * v for v in m["velocity"]]
    data.update(frames=frames, fps=fps, seed=seed)
    if offsets:
        data = parse_scenario(data).model_dump(mode="json")
        views = data["rig"]["views"]
        for view, off in zip(views, offsets, strict=True):
            view["time_offset_s"] = off
        data["rig"] = {**{k: v for k, v in data["rig"].items() if k != "ring"}, "views": views}
    return parse_scenario(data)


def _rmse(seen, method: str, rule: str) -> float:
    """Pooled 3-D RMSE (mm) of ``method`` over every marker under ``rule``."""
    sq = []
    for marker, Y in seen.aligned.items():
        est = create(method, seen.rig, seen.dt, {"pixel_sigma": seen.sigma})
        if rule == "previous rule":
            est.view_check = lambda: None  # a failed check drops the camera of largest own NIS
        elif rule == "without":
            est.joint_check = False
        sq.append(np.linalg.norm(est.run(Y).position - seen.truth.positions[marker], axis=1) ** 2)
    return 1000 * float(np.sqrt(np.nanmean(np.concatenate(sq))))


def measure(args: argparse.Namespace, root: Path) -> list[tuple[str, bool, float, dict]]:
    """(ring, held out, σ̂, {(method, rule): RMSE mm}) for every ring, rendered and detected here."""
    rows = []
    for name, spec in RINGS.items():
        clip = root / name.replace(" ", "_").replace(",", "").replace("(", "").replace(")", "")
        render_clip(scenario(*spec, args.frames), clip, fmt="mp4", workers=2)
        settings = RunSettings(images=False, recording=False, figures=False)
        detect_clip(clip, settings)
        seen = observe(Clip.open(clip), clip / "out", None, settings)
        cells = {(m, r): _rmse(seen, m, r) for m in ("triangulation", "ekf", "kf3d")
                 for r in (RULES if m != "triangulation" else RULES[:1])}
        rows.append((name, spec[-1], seen.sigma, cells))
        if args.verbose:
            print(f"  {name}: done", flush=True)
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=90)
    ap.add_argument("--verbose", action="store_true")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="stereotrack-joint-") as tmp:
        rows = measure(args, Path(tmp))
    print("# The joint check over three cameras or more\n")
    print(f"The ring scenario's three markers rendered ({args.frames} frames, 640×480, 2 px sensor noise), detected, σ "
          "estimated from the detections as `run` does; pooled 3-D RMSE (mm) over the markers.\n")
    print("| ring | set | σ̂ (px) | triangulation | EKF: with the check | previous rule | without | "
          "kf3d: with the check | previous rule | without |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, held, sigma, c in rows:
        print(f"| {name} | {'held out' if held else 'chosen on'} | {sigma:.3f} | {c['triangulation', RULES[0]]:.2f} | "
              + " | ".join(f"{c[m, r]:.2f}" for m in ("ekf", "kf3d") for r in RULES) + " |")
    print()
    for held in (False, True):
        part = [c for _, h, _, c in rows if h == held]
        for m in ("ekf", "kf3d"):
            ratio = [c[m, RULES[0]] / c[m, "without"] for c in part]
            prev = [c[m, "previous rule"] / c[m, "without"] for c in part]
            print(f"- {'Held out' if held else 'Chosen on'}, {m}: with the check below without on "
                  f"{sum(r < 1 for r in ratio)} of {len(ratio)} rings (with ÷ without: median {statistics.median(ratio):.2f}, "
                  f"{min(ratio):.2f}–{max(ratio):.2f}); the previous rule {statistics.median(prev):.2f} "
                  f"({min(prev):.2f}–{max(prev):.2f}).")


if __name__ == "__main__":
    page("joint_check", main)
