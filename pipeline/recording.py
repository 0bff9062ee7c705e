"""The rerun recording of a run (``out/run.rrd``; rerun-sdk pinned to 0.41).

Entity paths mirror the transform tree: ``/world`` is the left camera's frame; ``/world/left`` and
``/world/right`` carry each camera's ``Transform3D`` (from the calibration) and ``Pinhole``, logged
once as static data, with the frame image, detections and truth projections beneath them.
Trajectories live under ``/world/truth`` and ``/world/estimates/<method>``; per-frame errors under
``/metrics``. The blueprint (3-D view, both camera views, error plots) is built in code and saved
as the file's default.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.camera import StereoRig
from pipeline.io import atomic_path

PALETTE = [(230, 80, 60), (60, 160, 230), (90, 200, 90), (220, 180, 40), (170, 90, 220), (40, 200, 200),
           (240, 120, 200), (150, 150, 150)]


def blueprint(methods: list[str]):
    """3-D view beside the two camera views, error plots below."""
    import rerun.blueprint as rrb

    return rrb.Blueprint(
        rrb.Vertical(
            rrb.Horizontal(
                rrb.Spatial3DView(name="3-D", origin="/world"),
                rrb.Vertical(
                    rrb.Spatial2DView(name="left camera", origin="/world/left"),
                    rrb.Spatial2DView(name="right camera", origin="/world/right"),
                ),
                column_shares=[3, 2],
            ),
            rrb.Horizontal(
                rrb.TimeSeriesView(name="3-D error (m)", origin="/metrics/error"),
                rrb.TimeSeriesView(name="reprojection error (px)", origin="/metrics/reprojection"),
                rrb.TimeSeriesView(name="target α (rad)", origin="/metrics/target/alpha"),
                rrb.TimeSeriesView(name="target z (m)", origin="/metrics/target/distance"),
            ),
            row_shares=[3, 2],
        ),
        collapse_panels=True,
    )


def write_recording(
    path: str | Path,
    rig: StereoRig,
    dt: float,
    observations: dict[str, np.ndarray],
    tracks: dict[str, dict],
    truth: dict[str, np.ndarray] | None = None,
    frames=None,
    extra_series: dict[str, np.ndarray] | None = None,
    image_every: int = 1,
) -> Path:
    """Write the recording atomically. ``frames`` optionally yields (index, left, right) BGR images."""
    import cv2
    import rerun as rr

    path = Path(path)
    methods = list(tracks)
    with atomic_path(path) as tmp:
        rec = rr.RecordingStream("stereotrack")
        rec.save(tmp, default_blueprint=blueprint(methods))
        rec.log("world", rr.ViewCoordinates.RDF, static=True)  # OpenCV axes: x right, y down, z forward
        w, h = rig.image_size
        for cam, name in zip(rig.cameras, ("left", "right"), strict=True):
            R_wc, C = cam.R.T, cam.center
            rec.log(f"world/{name}", rr.Transform3D(translation=C, mat3x3=R_wc), static=True)
            rec.log(f"world/{name}", rr.Pinhole(image_from_camera=cam.K, width=w or None, height=h or None,
                                               camera_xyz=rr.ViewCoordinates.RDF), static=True)
        markers = list(observations)
        n = max((len(v) for v in observations.values()), default=0)
        images = {}
        if frames is not None:
            for k, left, right in frames:
                images[k] = (left, right)
        for k in range(n):
            rec.set_time("frame", sequence=k)
            rec.set_time("time", duration=k * dt)
            if k in images and k % image_every == 0:
                for img, name in zip(images[k], ("left", "right"), strict=True):
                    if img is not None:  # JPEG keeps a 150-frame stereo recording to a few MB
                        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 80])
                        if ok:
                            rec.log(f"world/{name}/image", rr.EncodedImage(contents=buf.tobytes(), media_type="image/jpeg"))
            for c, name in enumerate(("left", "right")):
                pts = [observations[m][k, 2 * c : 2 * c + 2] for m in markers]
                ok = [np.all(np.isfinite(p)) for p in pts]
                rec.log(f"world/{name}/detections", rr.Points2D([p for p, o in zip(pts, ok, strict=True) if o],
                                                                radii=3, colors=(255, 255, 0),
                                                                labels=[m for m, o in zip(markers, ok, strict=True) if o]))
                if truth is not None:
                    tp = np.array([truth[m][k] for m in markers if m in truth and k < len(truth[m])])
                    if len(tp):
                        rec.log(f"world/{name}/truth", rr.Points2D(rig.cameras[c].project(tp), radii=2, colors=(0, 255, 0)))
            if truth is not None:
                tp = np.array([truth[m][k] for m in markers if m in truth and k < len(truth[m])])
                if len(tp):
                    rec.log("world/truth/points", rr.Points3D(tp, radii=0.015, colors=(0, 255, 0)))
                    rec.log("world/truth/paths", rr.LineStrips3D([truth[m][: k + 1] for m in markers if m in truth],
                                                                 colors=(0, 200, 0)))
            for j, (meth, per_marker) in enumerate(tracks.items()):
                col = PALETTE[j % len(PALETTE)]
                cur = np.array([t.position[k] for t in per_marker.values()])
                fin = np.all(np.isfinite(cur), axis=1)
                rec.log(f"world/estimates/{meth}/points", rr.Points3D(cur[fin], radii=0.012, colors=col))
                strips = [t.position[: k + 1][np.all(np.isfinite(t.position[: k + 1]), axis=1)] for t in per_marker.values()]
                rec.log(f"world/estimates/{meth}/paths", rr.LineStrips3D([s for s in strips if len(s) > 1], colors=col))
                for marker, t in per_marker.items():
                    if truth is not None and marker in truth and k < len(truth[marker]):
                        e = float(np.linalg.norm(t.position[k] - truth[marker][k]))
                        if np.isfinite(e):
                            rec.log(f"metrics/error/{meth}/{marker}", rr.Scalars(e))
                    r = float(t.reprojection_error[k])
                    if np.isfinite(r):
                        rec.log(f"metrics/reprojection/{meth}/{marker}", rr.Scalars(r))
            for key, series in (extra_series or {}).items():
                if k < len(series) and np.isfinite(series[k]):
                    rec.log(f"metrics/{key}", rr.Scalars(float(series[k])))
        rec.flush()
        rec.disconnect()
    return path
