"""What a rendered clip folder holds besides its frames, and how it gets there: the truth,
timestamps, scenario, description and calibration written into a hidden staging folder, which is
committed into place only when complete; a folder stereotrack did not render is never replaced."""

from __future__ import annotations

import shutil
import warnings
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pipeline.core.calibration import save_calibration
from pipeline.core.camera import StereoRig
from pipeline.core.clip import CLIP_INFO, TIMESTAMPS
from pipeline.core.errors import StereotrackError
from pipeline.core.interrupts import raise_if_interrupted
from pipeline.core.io import check_replaceable, write_json, write_text
from pipeline.core.outputs import OUT
from pipeline.core.rig import Rig
from pipeline.core.rigfiles import save_rig
from renderers.motion import Truth, simulate_truth
from renderers.scenario import CalibrationErrorSpec, Scenario, clip_description
from renderers.truth import project_truth, write_target_truth, write_timestamps, write_truth
from renderers.writers import Format

#: an N-camera clip's calibration (a stereo clip's is calib.yaml)
RIG_FILE = "rig.json"


@dataclass
class RenderResult:
    """What a render produced."""

    clip_dir: Path
    frames: int
    warnings: list[str]
    cameras: tuple[str, ...] = ("left", "right")


def staging_dir(clip_dir: Path) -> Path:
    """The name of a fresh hidden folder beside ``clip_dir`` for one attempt at rendering it
    (stale ones of killed attempts are removed); the caller makes it."""
    import uuid

    for stale in clip_dir.parent.glob(f".{clip_dir.name}.partial-*"):
        shutil.rmtree(stale, ignore_errors=True)
    return clip_dir.parent / f".{clip_dir.name}.partial-{uuid.uuid4().hex[:12]}"


#: The file that says a folder is a clip stereotrack rendered (its description, with the keys
#: :func:`_is_our_description` checks; never ``scenario.yaml``, which a user writes): only such a
#: folder, or an empty one, is ever re-rendered.
RENDERED_MARK = (CLIP_INFO,)
#: What a render puts in a clip folder; a re-render replaces exactly these (and the stale ``out/``).
RENDERED = ("calib.yaml", "calib_true.yaml", RIG_FILE, CLIP_INFO, "scenario.yaml", "truth.csv", "target_truth.csv",
            TIMESTAMPS, "left", "right", "left.mp4", "right.mp4", OUT)
#: A marker counts as visible when at least this share of its unoccluded image area shows.
VISIBLE_SHARE = 0.4


def _is_our_description(path: Path) -> bool:
    """Whether ``path`` is a clip description the renderer wrote (a JSON object with its fps, frame
    count and markers), not a user's file of the same name."""
    import json

    try:
        info = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(info, dict) and {"fps", "frames", "markers"} <= info.keys()


def check_ours(clip_dir: Path) -> None:
    """Refuse, before any work, a folder that is neither new, empty nor a clip stereotrack rendered."""
    check_replaceable(clip_dir, RENDERED_MARK, "clip")
    info = clip_dir / CLIP_INFO
    if info.exists() and not _is_our_description(info):
        raise StereotrackError(f"{CLIP_INFO} here is not a clip description stereotrack wrote; choose an empty or "
                               "new folder for the clip", clip_dir)


def _rendered_cameras(clip_dir: Path) -> list[str]:
    """The camera files (``NAME.mp4``, ``NAME/``) an N-camera clip rendered here holds, by its clip.json."""
    import json

    try:
        names = json.loads((clip_dir / CLIP_INFO).read_text()).get("cameras") or []
    except (OSError, ValueError, AttributeError):
        return []
    return [f for n in names if isinstance(n, str) and n.replace("_", "").replace("-", "").isalnum()
            for f in (n, f"{n}.mp4")]


def _commit(staging: Path, clip_dir: Path) -> None:
    """Move a complete render into ``clip_dir``. A new folder is one rename; over an existing clip
    the old rendered files go first, calib.yaml first of all, and the new calib.yaml comes last,
    so an interrupted commit leaves a folder that is recognisably no clip (no calibration)."""
    raise_if_interrupted()  # nothing is committed once a signal came
    if not clip_dir.exists():
        staging.rename(clip_dir)
        return
    for name in (*RENDERED, *_rendered_cameras(clip_dir)):
        p = clip_dir / name
        if p.is_dir():
            shutil.rmtree(p)
        elif p.exists():
            p.unlink()
    for p in sorted(staging.iterdir(), key=lambda p: p.name in ("calib.yaml", RIG_FILE)):
        p.rename(clip_dir / p.name)
    staging.rmdir()


def _write_clip_files(scenario: Scenario, staging: Path, truth: Truth, fmt: Format,
                      counts: list[np.ndarray | None]) -> list[str]:
    """Truth, timestamps, scenario, description and calibration beside the frames (the user's
    calibration, perturbed when a calibration error is asked for, with the true one beside it);
    returns notes (markers never in view)."""
    rig = scenario.rig.build_any()
    names = scenario.rig.camera_names()
    proj = project_truth(rig, scenario, truth, distractors=all(c is None for c in counts))
    for c, cnt in enumerate(counts):
        if cnt is not None:  # the rendered image decides: occluded or cut by the frame ⇒ not visible
            proj.visible[:, :, c] &= cnt >= VISIBLE_SHARE * expected_areas(rig.cameras[c], truth, proj, c)
    notes = [f"marker '{name}' is never visible in {'either camera' if len(names) == 2 else 'any camera'}"
             for i, name in enumerate(truth.names) if not proj.visible[:, i, :].any()]
    info = clip_description(scenario)
    write_text(staging / "scenario.yaml", scenario.to_yaml())
    write_json(staging / CLIP_INFO, info)
    write_truth(staging / "truth.csv", truth, proj, names, {m["name"]: m["group"] for m in info["markers"]})
    write_timestamps(staging / TIMESTAMPS, proj.times, fmt, names)
    if isinstance(rig, Rig):  # N cameras: the rig file of its own format (no stereo calib.yaml)
        save_rig(rig, staging / RIG_FILE)
        return notes
    if truth.targets:
        write_target_truth(staging / "target_truth.csv", truth, proj)
    if scenario.calibration_error is not None:
        save_calibration(rig, staging / "calib_true.yaml")
        rig = perturbed_rig(rig, scenario.calibration_error, scenario.seed)
    save_calibration(rig, staging / "calib.yaml")
    return notes


def expected_areas(cam, truth: Truth, proj, c: int) -> np.ndarray:
    """Each marker's unoccluded image area (px², frames × markers): a sphere's disc, a flat disc
    foreshortened by its tilt."""
    n, m = truth.positions.shape[:2]
    out = np.zeros((n, m))
    f = float(np.sqrt(cam.K[0, 0] * cam.K[1, 1]))
    for i in range(m):
        p, _, nrm = truth.at(proj.t_seen[:, i, c], [i])
        p, nrm = p[:, 0], nrm[:, 0]
        z = np.maximum(cam.depth(p), 1e-6)
        area = np.pi * (f * truth.radii[i] / z) ** 2
        if np.all(np.isfinite(nrm)):
            ray = cam.center - p
            area *= np.abs(np.einsum("ij,ij->i", nrm, ray)) / np.linalg.norm(ray, axis=1)
        out[:, i] = area
    return out


def perturbed_rig(rig: StereoRig, err: CalibrationErrorSpec, seed: int) -> StereoRig:
    """The calibration a user would have: focal lengths, principal points, baseline length, the
    second camera's rotation and k1, k2 perturbed by the spec's standard deviations, drawn from
    ``[err.seed or seed, 50000]``."""
    from pipeline.core.camera import Camera

    rng = np.random.default_rng([err.seed if err.seed is not None else seed, 50_000])

    def camera_K(K: np.ndarray) -> np.ndarray:
        K = K.copy()
        K[0, 0] *= 1 + err.focal * rng.standard_normal()
        K[1, 1] *= 1 + err.focal * rng.standard_normal()
        K[:2, 2] += err.principal_point * rng.standard_normal(2)
        return K

    def dist(D: np.ndarray) -> np.ndarray:
        D = D.copy()
        D[:2] += err.distortion * rng.standard_normal(2)
        return D

    K1, K2, D1, D2 = camera_K(rig.left.K), camera_K(rig.right.K), dist(rig.left.D), dist(rig.right.D)
    rvec = np.radians(err.rotation_deg) * rng.standard_normal(3)
    R = cv2.Rodrigues(rvec)[0] @ rig.R
    C = rig.right.center * (1 + err.baseline * rng.standard_normal())
    return StereoRig(Camera(K1, D=D1), Camera(K2, R, -R @ C, D2), rig.image_size)


def finish_clip(scenario: Scenario, staging: Path, clip_dir: Path, fmt: Format,
                 counts: list[np.ndarray | None], truth: Truth | None = None) -> RenderResult:
    """Write the truth (``truth``, or simulated again) and calibration of a clip whose frames are
    all in ``staging``, commit it, and warn about its notes."""
    notes = _write_clip_files(scenario, staging, truth if truth is not None else simulate_truth(scenario), fmt,
                              counts)
    _commit(staging, clip_dir)
    for msg in notes:
        warnings.warn(f"{clip_dir}: {msg}", stacklevel=3)
    return RenderResult(clip_dir, scenario.frames, notes, scenario.rig.camera_names())
