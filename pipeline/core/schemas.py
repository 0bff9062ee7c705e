"""The schemas of every table a clip or its ``out/`` folder holds (``truth.csv`` with a column set
per camera, ``timestamps.csv``, ``detections.csv``, estimates): what each column means, written
into the docs and checked by the readers."""

from __future__ import annotations

from pipeline.core.io import Schema

_FRAME = "frame index, from 0"
_XYZ = dict.fromkeys("xyz", "position in the world frame (the left camera's: x right, y down, z forward), m")
_VXYZ = dict.fromkeys(("vx", "vy", "vz"), "velocity, m/s")
_TARGET_PX = {f"{c}{i}_{cam}": "pixel (u, v) of target point i (1–4) in the named camera, as its lens images it, px"
              for cam in ("left", "right") for i in range(1, 5) for c in ("u", "v")}

STEREO = ("left", "right")


def _truth_schema(cameras: tuple[str, ...]) -> dict[str, str]:
    return {
        "frame": _FRAME,
        "t": f"the {cameras[0]} camera's frame time, s",
        "marker": "the marker's name",
        **_XYZ, **_VXYZ,
        **{f"{c}_{cam}": f"pixel in the {cam} camera, as its lens images the marker at that camera's own time, px"
           for cam in cameras for c in "uv"},
        **{f"visible_{cam}": f"1 where the marker is in the {cam} camera's image and not hidden, else 0"
           for cam in cameras},
    }


def _truth_extra_schema(cameras: tuple[str, ...]) -> dict[str, str]:
    """Written by the renderer after the columns readers ask for: each camera's pixels without lens
    distortion and the time each camera saw the marker."""
    return {
        **{f"{c}_{cam}_pinhole": f"pixel in the {cam} camera without lens distortion (what undistorted detections "
           "are compared with), px" for cam in cameras for c in "uv"},
        **{f"t_{cam}": f"when the {cam} camera saw the marker: its frame time plus, with a rolling shutter, the delay "
           "of the row that imaged it, s" for cam in cameras},
        "group": "what a detector sees the marker as: the group of identical markers it belongs to (the name "
                 "detections.csv gives their blobs), or its own name",
    }


def truth_columns(cameras: tuple[str, ...] = STEREO) -> list[str]:
    """``truth.csv``'s columns for a clip with these cameras (left, right: a stereo clip)."""
    return list(_truth_schema(cameras))


def truth_extra_columns(cameras: tuple[str, ...] = STEREO) -> list[str]:
    return list(_truth_extra_schema(cameras))


_TRUTH = _truth_schema(STEREO)
_TRUTH_EXTRA = _truth_extra_schema(STEREO)
TRUTH = Schema("truth.csv", "one marker at one frame", "render", {**_TRUTH, **_TRUTH_EXTRA})
TIMESTAMPS = "timestamps.csv"
TIMESTAMPS_SCHEMA = Schema(TIMESTAMPS, "one frame of one camera's footage (a dropped frame has no row)",
                           "render, or you (real footage)", {
    "frame": "the footage's own frame number: a video's position, a PNG's file number",
    "camera": "left or right (an N-camera clip: the camera's name in its rig file)",
    "t": "when the camera exposed the frame's first row, s",
})
TARGET_TRUTH = Schema("target_truth.csv", "one frame of the four-point target", "render", {
    "frame": _FRAME,
    "t": "the left camera's frame time, s",
    "alpha": "the plate's tilt α about its axis, rad",
    "alpha_dot": "dα/dt, rad/s",
    "distance": "the plate centre's distance along the optical axis, m",
    "distance_dot": "its rate, m/s",
    "axis_angle": "the tilt axis's in-image rotation about the optical axis, rad",
    **_TARGET_PX,
})
DETECTIONS = Schema("out/detections.csv", "one detection (a camera may have none for a marker at a frame)", "detect", {
    "frame": _FRAME,
    "camera": "left or right (an N-camera clip: the camera's name in its rig file)",
    "marker": "the marker's name",
    "u": "pixel, undistorted by the calibration, px",
    "v": "pixel, undistorted by the calibration, px",
    "area": "the blob's area, px²",
    "score": "the detector's confidence in [0, 1]: the blob's roundness, or the tracker's share of the colour mass",
    "index": "the detection's number among this marker's (or group's) detections in this frame and camera, from 0, "
             "best first: a group of identical markers has several, with no identity (written by detect; a file of "
             "your own may leave it out)",
    "merged": "1 where a group's blob has over 1.4× the group's median blob area in this camera (the median over "
              "the frame and the 15 on either side) and a roundness under 0.8: the images of two or more markers "
              "merged; else 0 (written by detect; a file of your own may leave it out). The association updates no "
              "track from a merged blob's centroid and starts none from it",
})

ESTIMATES = Schema("out/estimates/<method>.csv", "one marker at one frame", "estimate", {
    "frame": _FRAME,
    "t": "the frame time, s",
    "marker": "the marker's name",
    **_XYZ, **_VXYZ,
    "nis": "normalised innovation squared of the frame's update (filters; empty otherwise)",
    "nis_dof": "its degrees of freedom: the number of measured values the update used (2 per camera for pixel filters)",
    "nees": "position NEES against the truth (filters on rendered clips; empty otherwise)",
    "predicted": "1 where the method used no measurement (a gap, a gated frame, before its start: the position "
                 "is held or coasted), 0 where it did",
    "group": "the group of identical markers a track (``<group>#<n>``) belongs to; a marker of its own colour: its "
             "own name",
})
TARGET_ESTIMATES = Schema("out/estimates/<four-point method>.csv", "one frame (marker: the target's name)", "estimate", {
    "alpha": "the estimated tilt α, rad",
    "distance": "the estimated distance of the plate centre, m",
}, extends=ESTIMATES)
SCHEMAS = (TRUTH, TIMESTAMPS_SCHEMA, TARGET_TRUTH, DETECTIONS, ESTIMATES, TARGET_ESTIMATES)

TRUTH_COLUMNS = list(_TRUTH)
TRUTH_EXTRA_COLUMNS = list(_TRUTH_EXTRA)
TIMESTAMP_COLUMNS = TIMESTAMPS_SCHEMA.names
TARGET_TRUTH_COLUMNS = TARGET_TRUTH.names
DETECTION_WRITTEN = DETECTIONS.names
#: the columns a detections.csv must have (``index`` and ``merged`` are optional)
DETECTION_COLUMNS = DETECTION_WRITTEN[:-2]
ESTIMATE_COLUMNS = ESTIMATES.names
TARGET_COLUMNS = TARGET_ESTIMATES.names
