"""Checks that catch inputs which are wrong in ordinary ways — left/right swapped, a calibration for
another image size, detections that do not correspond between the cameras, a colour range that
matches the background or a second object, points behind a camera — so that garbage is reported,
never scored silently. Each check is a :class:`Check` record (written to ``metrics.json`` under
``checks`` and to the report's "Checks" section); a failed one is also a one-line warning.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from pipeline.core.camera import StereoRig, Views
from pipeline.core.errors import ClipError
from pipeline.core.rig import Rig

#: Median epipolar distance (px) of matched detections above which the cameras' detections are
#: taken not to correspond (a rendered clip gives ~0.1 px, a good real rig well under 1 px).
EPIPOLAR_WARN_PX = 3.0
#: Fraction of triangulated points behind a camera above which left/right look swapped.
SWAPPED_FRACTION = 0.5
#: A detection moving more than this fraction of the image width between consecutive frames
#: moves farther than a tracked marker plausibly can (a thrown ball crosses ~0.1 per frame).
JUMP_FRACTION = 0.25
#: A colour range whose mask is this many times the detected blob's area matches more than one marker.
MASK_TO_BLOB = 8.0
#: A colour range selecting more than this fraction of a frame matches the background (a marker
#: that close fills the view and cannot be tracked as a point anyway).
MASK_FRACTION = 0.25
#: a mask with this share of its pixels in one connected part is one object, not the background
ONE_OBJECT = 0.8


@dataclass
class Check:
    """One input check: ``ok`` False means the user must look (the message says at what)."""

    name: str
    ok: bool
    message: str
    value: float | None = None
    subject: str = ""  # the marker or file it concerns

    def as_dict(self) -> dict:
        return asdict(self)


def warn_failed(checks: list[Check]) -> None:
    """Emit each failed check as a one-line warning."""
    for c in checks:
        if not c.ok:
            warnings.warn(c.message, stacklevel=2)


def rig_for_frames(rig: StereoRig, frame_size: tuple[int, int], calib: str | Path) -> tuple[StereoRig, Check | None]:
    """The rig for frames of ``frame_size``: unchanged when the calibration's image size matches
    (or is not given); scaled, with a failed check, when only the resolution differs (same aspect
    ratio, e.g. a 1280×720 calibration on 640×360 video); an error naming both sizes otherwise."""
    cw, ch = rig.image_size
    fw, fh = frame_size
    if (cw, ch) == (0, 0):
        return rig, unsized_calibration_check(rig, frame_size, calib)
    if (cw, ch) == (fw, fh):
        return rig, None
    if abs(cw / ch - fw / fh) > 1e-3 * (fw / fh):
        raise ClipError(f"the calibration is for {cw}×{ch} images but the frames are {fw}×{fh} "
                        "(another aspect ratio: recalibrate at this size)", calib)
    msg = (f"{calib}: the calibration is for {cw}×{ch} images but the frames are {fw}×{fh}; "
           f"scaled K by {fw / cw:g} (same aspect ratio)")
    return rig.scaled_to((fw, fh)), Check("image_size", False, msg, fw / cw, str(calib))


def check_view_sizes(rig: Rig, frame_sizes: list[tuple[int, int]], calib: str | Path) -> None:
    """An N-camera rig against its footage: each camera's calibrated image size must be its
    frames' size (an error naming the camera and both sizes)."""
    for name, (cw, ch), (fw, fh) in zip(rig.names, rig.sizes, frame_sizes, strict=True):
        if (cw, ch) != (fw, fh):
            raise ClipError(f"camera {name}: the calibration is for {cw}×{ch} images but its frames are {fw}×{fh}", calib)


def unsized_calibration_check(rig: StereoRig, frame_size: tuple[int, int], calib: str | Path) -> Check | None:
    """For a calibration that does not record its image size (OpenCV's ``stereo_calib`` layout):
    a principal point sitting where the centre of an image ``s`` times the frames' size would be
    (the same ``s`` in x and y, for both cameras, ``s`` not near 1) names the likely size it was
    made at. Without this, a 320×240 calibration on 640×480 frames reads as "left/right swapped"."""
    fw, fh = frame_size
    ratios = []
    for cam in rig.cameras:
        cx, cy = cam.K[0, 2], cam.K[1, 2]
        ratios += [(cx + 0.5) / (fw / 2), (cy + 0.5) / (fh / 2)]
    s = float(np.median(ratios))
    if abs(s - 1) < 0.2 or max(abs(r / s - 1) for r in ratios) > 0.1:
        return None
    common = min((0.25, 1 / 3, 0.5, 2 / 3, 0.75, 1.5, 2.0, 3.0, 4.0), key=lambda c: abs(c / s - 1))
    s = common if abs(common / s - 1) < 0.05 else s  # principal points are never exactly central
    msg = (f"{calib}: the calibration does not say its image size, and its principal points sit at the centre of "
           f"a {fw * s:.0f}×{fh * s:.0f} image, not of these {fw}×{fh} frames: it was likely made at that size "
           f"(recalibrate at this size, or add image_width/image_height to the file so that K is scaled)")
    return Check("calibration_size", False, msg, s, str(calib))


def stereo_checks(rig: StereoRig, observations: dict[str, np.ndarray], calib: str = "calib.yaml") -> list[Check]:
    """Left/right swapped (most triangulations behind a camera), non-corresponding detections
    (median epipolar distance) and points behind a camera, over all markers' two-camera frames."""
    from pipeline.core.camera import triangulate

    Y = np.vstack([v for v in observations.values()]) if observations else np.empty((0, 4))
    Y = Y[np.all(np.isfinite(Y), axis=1)]
    if len(Y) == 0:
        return [Check("stereo_pairs", False, "no frame has a detection in both cameras: nothing can be triangulated")]
    X = triangulate(rig, Y)
    fin = np.all(np.isfinite(X), axis=1)
    depth = rig.depths(X[fin])
    behind = np.any(depth <= 0, axis=1)
    frac = float(behind.mean()) if len(behind) else 0.0
    out = []
    if frac > SWAPPED_FRACTION:
        Xs = triangulate(rig, Y[:, [2, 3, 0, 1]])
        ok = np.all(np.isfinite(Xs), axis=1)
        front_swapped = float(np.all(rig.depths(Xs[ok]) > 0, axis=1).mean()) if ok.any() else 0.0
        out.append(Check("left_right", False,
                         f"left/right videos look swapped against {calib}: {frac:.0%} of triangulated points lie behind "
                         f"a camera ({front_swapped:.0%} in front with the videos exchanged)", frac))
    else:
        out.append(Check("left_right", True, f"{1 - frac:.0%} of triangulated points in front of both cameras", frac))
    epi = float(np.nanmedian(rig.epipolar_distance(Y)))
    if epi > EPIPOLAR_WARN_PX:
        out.append(Check("epipolar", False,
                         f"detections do not correspond between the cameras: median epipolar distance {epi:.1f} px "
                         f"(> {EPIPOLAR_WARN_PX:g} px): wrong calibration, unsynchronised videos or different objects "
                         "matched", epi))
    else:
        out.append(Check("epipolar", True, f"median epipolar distance {epi:.2f} px", epi))
    n_behind = int(behind.sum())
    out.append(Check("behind_camera", n_behind == 0,  # failed with the swap too: points behind are never "ok"
                     f"{n_behind} of {len(behind)} triangulated points lie behind a camera (excluded from the figures)",
                     float(n_behind)))
    return out


def jump_checks(observations: dict[str, np.ndarray], image_width: int) -> list[Check]:
    """Per marker: detections that move more than :data:`JUMP_FRACTION` of the image width between
    consecutive frames (the tracker jumped to another object of the marker's colour)."""
    out = []
    limit = JUMP_FRACTION * image_width
    for name, Y in observations.items():
        jumps = 0
        for c in range(2):
            uv = Y[:, 2 * c : 2 * c + 2]
            d = np.linalg.norm(np.diff(uv, axis=0), axis=1)
            jumps += int(np.sum(d[np.isfinite(d)] > limit))
        if jumps >= 3:
            out.append(Check("track_jumps", False,
                             f"marker '{name}' jumps more than {limit:.0f} px between consecutive frames {jumps} times: "
                             "its colour range probably matches another object", float(jumps), name))
    return out


def colour_checks(samples: dict[tuple[str, str], list[tuple[float, ...]]]) -> list[Check]:
    """Per marker and camera, from sampled whole frames: (mask fraction of the frame, mask pixels,
    largest blob area, second-largest blob area, the largest connected part's share of the mask).
    A range whose mask is far larger than the blob it finds matches the background, unless the
    mask is one object (``ONE_OBJECT`` of it in one connected part: a large marker, a tray, that
    the blob filters measure smaller); two blobs of comparable size in most frames mean a second
    object of the marker's colour."""
    out = []
    for (name, cam), rows in samples.items():
        if not rows:
            continue
        a = np.array(rows, dtype=float)
        frac, mask_px, big = (np.median(a[:, i]) for i in range(3))
        one_object = a.shape[1] > 4 and np.median(a[:, 4]) >= ONE_OBJECT
        if frac > MASK_FRACTION or (frac > 0.02 and mask_px > MASK_TO_BLOB * max(big, 1.0) and not one_object):
            out.append(Check("colour_range", False,
                             f"marker '{name}': its colour range selects {frac:.0%} of the {cam} frame ({mask_px:,.0f} px "
                             f"against a blob of {big:,.0f} px): it matches the background; narrow the range",
                             float(frac), name))
            continue
        multi = float(np.mean((a[:, 3] >= 0.25 * a[:, 2]) & (a[:, 3] > 0)))
        if multi > 0.5:
            out.append(Check("colour_range", False,
                             f"marker '{name}': two or more blobs of its colour in {multi:.0%} of sampled {cam} frames: "
                             "another object of the same colour may be tracked instead", multi, name))
    return out


#: a marker found in fewer than this share of a camera's frames is worth a look
RARE_SHARE = 0.25


def rarely_found_checks(cols: dict[str, np.ndarray], frames: int, cameras: tuple[str, ...],
                        markers: list[str]) -> list[Check]:
    """Per marker and camera: found in under :data:`RARE_SHARE` of the frames (of a clip of ten or
    more), its colour range most likely misses it (learned from one frame's lighting, say), and a
    table of dashes is no result to pass on without a word."""
    if frames < 10:
        return []
    out = []
    for cam in cameras:
        for name in markers:
            mine = (cols["camera"] == cam) & (cols["marker"] == name)
            n = len(np.unique(cols["frame"][mine]))
            if n < RARE_SHARE * frames:
                out.append(Check("detection_rate", False,
                                 f"marker '{name}' found in {n} of {frames} {cam} frames: its colour range misses it "
                                 "(learn it again from a window where it shows, or widen it)", n / frames, name))
    return out


#: camera centres farther apart than this (m) are a unit mistake (a board square given without
#: its unit is metres), not a rig; closer than :data:`MIN_SPACING_M`, one in millimetres read as metres
MAX_SPACING_M = 100.0
MIN_SPACING_M = 0.005
#: focal lengths outside these multiples of the image width (a field of view over 146° or under
#: 1.2°) are no calibration of this footage
FOCAL_TO_WIDTH = (0.15, 50.0)


def calibration_checks(views: Views, calib: str = "calib.yaml") -> list[Check]:
    """The calibration's scale and focal lengths against what a rig can be: cameras 300 m apart
    (a calibration from ``--square 25`` read as metres) or a focal length of a 1° lens pass every
    other check and turn every 3-D figure into nonsense, so they are failed checks naming the file."""
    out = []
    centres = np.array([cam.center for cam in views.cameras])
    spacing = np.linalg.norm(centres[:, None] - centres[None], axis=2)[np.triu_indices(len(centres), 1)]
    if len(spacing) and (spacing.max() > MAX_SPACING_M or spacing.min() < MIN_SPACING_M):
        far = spacing.max() if spacing.max() > MAX_SPACING_M else spacing.min()
        out.append(Check("calibration_scale", False, f"{calib}: cameras {far:.4g} m apart: is the calibration in the "
                         "unit it states (a board square given without its unit is metres)?", float(far), calib))
    for cam, name, (w, _) in zip(views.cameras, views.names, views.sizes, strict=True):
        f = float(cam.K[0, 0])
        if w and not FOCAL_TO_WIDTH[0] * w <= f <= FOCAL_TO_WIDTH[1] * w:
            fov = float(np.degrees(2 * np.arctan(w / (2 * f)))) if f > 0 else float("nan")
            out.append(Check("calibration_focal", False, f"{calib}: the {name} camera's focal length {f:.4g} px is "
                             f"{f / w:.3g}× the image width {w} px (a {fov:.3g}° field of view): not this footage's "
                             "calibration?", f / w, calib))
    return out
