"""The rerun viewer's layout for a run (the blueprint, built in code) and the 3-D view's framing:
what a person sees at first open, chosen from the run itself (its ranking, its runaways, its tracks)."""

from __future__ import annotations

import numpy as np

#: methods shown in the 3-D and error views at first open (the best by the run's ranking); the rest one click away
SHOWN_METHODS = 3


def _legend():
    """The plots' legend: in the top-right corner (its series one click from hidden)."""
    import rerun.blueprint as rrb

    return rrb.PlotLegend(corner=rrb.Corner2D.RightTop, visible=True)


def _hidden(paths: list[str]):
    import rerun.blueprint as rrb

    return {p: rrb.EntityBehavior(visible=False) for p in paths}


def _series_tabs(kind: str, title: str, markers: list[str], hidden: list[str], *more):
    """One time-series view per marker (one line per method), as tabs, then ``more`` views; ``hidden``
    methods (runaways, and those after the best few) hidden until shown, so the legend in its corner
    stays short."""
    import rerun.blueprint as rrb

    views = [rrb.TimeSeriesView(name=f"{title} · {mk}", origin=f"/metrics/{kind}/{mk}", plot_legend=_legend(),
                                overrides=_hidden([f"/metrics/{kind}/{mk}/{m}" for m in hidden]) or None)
             for mk in markers] + list(more)
    return rrb.Tabs(*views) if views else None


def blueprint(fps: float = 30.0, target: bool = False, info: bool = False, markers: list[str] | None = None,
              hidden: list[str] | None = None, uncertain: list[str] | None = None,
              cameras: tuple[str, ...] = ("left", "right"), tucked: list[str] | None = None,
              eye: tuple[np.ndarray, np.ndarray] | None = None, truth: bool = True, camera_off: list[str] | None = None,
              banded: list[str] | None = None):
    """3-D view (each point at the cursor over its static path) beside the camera views; below,
    per marker, the 3-D and reprojection errors with one line per method, and the four-point
    target's α and z when the run has the target; the run's description when given. ``hidden``
    (runaway methods) start hidden everywhere, ``tucked`` (the methods after the best few) in the
    3-D, camera and error views, and the covariance ellipsoids of ``uncertain`` too: one click in the
    blueprint tree shows each; ``camera_off`` (when given) are the methods the camera views hide: all
    but the best, one cross per marker, not a pile of colours on one pixel. ``eye``: (position, look
    target) of the 3-D view; without ``truth`` no 3-D error plots (they would stay empty); the markers
    ``banded`` get a tab each of the filters' depth errors with their ±σ bands. The time
    panel opens on the ``frame`` timeline at the clip's frame rate."""
    import rerun.blueprint as rrb

    hidden, markers, tucked = list(hidden or []), list(markers or []), list(tucked or [])
    off_cameras = hidden + tucked if camera_off is None else list(camera_off)
    lanes = rrb.StateTimelineView(name="track state", origin="/state",
                                  overrides=_hidden([f"/state/{m}" for m in hidden + tucked]) or None)
    depth = [rrb.TimeSeriesView(name=f"depth error ±σ (mm) · {mk}", origin=f"/metrics/depth/{mk}", plot_legend=_legend(),
                                overrides=_hidden([f"/metrics/depth/{mk}/{m}" for m in hidden + tucked]) or None)
             for mk in banded or []]
    plots = [t for t in (_series_tabs("error", "3-D error (mm)", markers if truth else [], hidden + tucked, *depth),
                         _series_tabs("reprojection", "reprojection error (px)", markers, hidden + tucked, lanes))
             if t is not None]
    if target:
        plots += [rrb.TimeSeriesView(name="target α (mrad)", origin="/metrics/target/alpha", plot_legend=_legend()),
                  rrb.TimeSeriesView(name="target z (mm)", origin="/metrics/target/distance", plot_legend=_legend())]
    side: list[rrb.Spatial2DView | rrb.TextDocumentView | rrb.Grid] = [rrb.Spatial2DView(name=f"{c} camera", origin=f"/world/{c}",
                              overrides=_hidden([f"/world/{c}/estimates/{m}" for m in off_cameras]) or None)
            for c in cameras]
    if info:
        side.append(rrb.TextDocumentView(name="this run", origin="/run"))
    if len(cameras) > 2:  # N cameras: a grid of camera views beside the 3-D view
        side = [rrb.Grid(*side)]
    off = [f"/world/estimates/{m}" for m in hidden + tucked] + [f"/world/uncertainty/{m}" for m in uncertain or []]
    controls = None if eye is None else rrb.EyeControls3D(position=eye[0], look_target=eye[1], eye_up=(0.0, -1.0, 0.0))
    view3d = rrb.Spatial3DView(name="3-D", origin="/world", overrides=_hidden(off) or None, eye_controls=controls)
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(view3d, rrb.Vertical(*side), column_shares=[3, 2]), rrb.Horizontal(*plots),
                     row_shares=[3, 2]),
        rrb.TimePanel(timeline="frame", fps=float(fps), play_state="paused"),
        collapse_panels=True,
    )


def framing(points: np.ndarray, fov_deg: float = 60.0) -> tuple[np.ndarray, np.ndarray] | None:
    """An eye (position, look target) that frames ``points`` (n × 3, left camera frame, y down):
    the 2–98 % box of the points in a three-quarter view (from the cameras' side, the right and
    above: a path along the cameras' axis is seen at length, not end on), at the distance where the
    box's diagonal fills the view's height."""
    P = points[np.all(np.isfinite(points), axis=1)]
    if len(P) < 2:
        return None
    lo, hi = np.percentile(P, [2, 98], axis=0)
    centre, size = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)), 0.05)
    back = -centre / (np.linalg.norm(centre) or 1.0)  # towards the cameras (the world origin)
    view = 0.7 * back + np.array([0.7, -0.45, 0.0])  # right of and above the paths (y is down)
    view /= np.linalg.norm(view)
    distance = 0.52 * size / np.tan(np.radians(fov_deg) / 2)
    return centre + distance * view, centre


