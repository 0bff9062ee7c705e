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


#: the 3-D view as the viewer shows it in the default layout: vertical field of view (degrees) and
#: width / height of the pane (3 of 5 columns, 3 of 5 rows of a 16:10 to 16:9 window)
VIEW_FOV_Y, VIEW_ASPECT = 55.0, 2.4
#: the share of the view's half-width or half-height the framed points reach (the larger of the two)
FILL = 0.85
#: how far above the paths the eye may look down from (degrees)
ELEVATIONS = (20.0, 35.0, 50.0)
#: a marker's label in the view's normalised units (−1…1 across: width, height; ~60 × 18 px in a
#: 1,150 × 440 px pane), and what a view whose labels overlap scores against one whose do not
LABEL, CROWDED = (0.11, 0.085), 0.25
#: the nearest point stays at least this many times the points' spread in depth from the eye (a
#: compact path would otherwise be framed from so close that its near side swells)
NEAR = 0.5


def framing(paths: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray] | None:
    """An eye (position, look target) that frames the markers' ``paths`` (each frames × 3, left
    camera frame, y down; NaN where unknown): of the directions on the cameras' side of them
    (azimuths within 80° of the way back to the cameras, :data:`ELEVATIONS` above them), the one
    from which, centred and brought as close as :func:`_fit` allows, their image's box fills most of
    the view (:data:`VIEW_FOV_Y`, :data:`VIEW_ASPECT`) with the markers' labels apart at the first,
    middle and last frames (:func:`_labels_apart`): a path seen end on, or a streak along the view's
    short side, fills little, and a target seen edge on piles its labels up."""
    P = np.vstack(paths) if paths else np.empty((0, 3))
    P = P[np.all(np.isfinite(P), axis=1)]
    if len(P) < 2:
        return None
    lo, hi = P.min(axis=0), P.max(axis=0)
    centre, size = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)), 0.05)
    sample = P[:: max(1, len(P) // 200)]  # the search on a sample; the chosen view fitted on all
    back = -centre / (np.linalg.norm(centre) or 1.0)
    base = np.arctan2(back[0], back[2])
    views = [np.array([np.cos(el) * np.sin(az), -np.sin(el), np.cos(el) * np.cos(az)])  # y is down: up is −y
             for el in np.radians(ELEVATIONS) for az in base + np.radians(np.arange(-80, 81, 20))]
    moments = _moments(paths)

    def score(view: np.ndarray) -> float:
        eye, target, filled = _fit(sample, centre, view, size, rounds=3, steps=8)
        return filled * (1.0 if _labels_apart(moments, eye, target) else CROWDED)

    eye, target, _ = _fit(P, centre, max(views, key=score), size)
    return eye, target


def _moments(paths: list[np.ndarray]) -> list[np.ndarray]:
    """The markers' positions (markers × 3, NaN where unknown) at the first, middle and last frames."""
    n = min((len(p) for p in paths), default=0)
    return [np.stack([p[k] for p in paths]) for k in sorted({0, n // 2, n - 1})] if n else []


def _labels_apart(moments: list[np.ndarray], eye: np.ndarray, target: np.ndarray) -> bool:
    """Whether no two markers' labels (a box :data:`LABEL` wide and tall, in the view's normalised
    units, below each point) overlap at any of the ``moments``."""
    for X in moments:
        ok = np.all(np.isfinite(X), axis=1)
        if ok.sum() < 2:
            continue
        ndc = _project(X[ok], eye, target)[0]
        dx, dy = (np.abs(ndc[:, None, i] - ndc[None, :, i]) for i in (0, 1))
        close = (dx < LABEL[0]) & (dy < LABEL[1])
        if np.any(close[np.triu_indices(len(ndc), 1)]):
            return False
    return True


def _fit(P: np.ndarray, centre: np.ndarray, view: np.ndarray, size: float, rounds: int = 30, steps: int = 24
         ) -> tuple[np.ndarray, np.ndarray, float]:
    """The eye along ``view`` that centres the points' image (half steps: perspective) at the
    distance where they reach :data:`FILL` of the view, or their nearest point :data:`NEAR` times
    their spread in depth; with the share of the view their image's box fills."""
    target, distance = centre, size
    for _ in range(rounds):
        step = 0.5 * _image_offset(P, target + distance * view, target)
        target = target + step
        distance = _fitting_distance(P, target, view, distance, steps)
        if np.linalg.norm(step) < 1e-3 * size:
            break
    ndc = _project(P, target + distance * view, target)[0]
    return target + distance * view, target, float(np.prod(np.ptp(ndc, axis=0)) / 4)


def _basis(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The view's forward, right and up unit vectors (up: the world's −y, as ``eye_up``), written
    out: ``np.cross`` on 3-vectors is what made the framing's search slow."""
    fx, fy, fz = (target - eye) / np.linalg.norm(target - eye)
    n = np.hypot(fz, fx) or 1.0
    rx, rz = fz / n, -fx / n  # f × (0, −1, 0), normalised
    return np.array([fx, fy, fz]), np.array([rx, 0.0, rz]), np.array([-rz * fy, rz * fx - rx * fz, rx * fy])


def _project(P: np.ndarray, eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``P`` in the view's normalised coordinates (−1…1 across the view: x right, y up) and depth."""
    f, r, u = _basis(eye, target)
    rel = P - eye
    depth = rel @ f
    ty = np.tan(np.radians(VIEW_FOV_Y) / 2)
    ndc = np.column_stack([rel @ r / (depth * ty * VIEW_ASPECT), rel @ u / (depth * ty)])
    return ndc, depth


def _image_offset(P: np.ndarray, eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The move of the look target (and eye with it) that centres the points' image in the view."""
    ndc = _project(P, eye, target)[0]
    mid = (ndc.min(axis=0) + ndc.max(axis=0)) / 2
    _, r, u = _basis(eye, target)
    ty, d = np.tan(np.radians(VIEW_FOV_Y) / 2), float(np.linalg.norm(target - eye))
    return mid[0] * d * ty * VIEW_ASPECT * r + mid[1] * d * ty * u


def _fits(P: np.ndarray, eye: np.ndarray, target: np.ndarray) -> bool:
    ndc, depth = _project(P, eye, target)
    return bool(depth.min() > NEAR * np.ptp(depth) and np.abs(ndc).max() <= FILL)


def _fitting_distance(P: np.ndarray, target: np.ndarray, view: np.ndarray, start: float, steps: int = 40) -> float:
    """The eye's distance along ``view`` at which the points reach :data:`FILL` of the view (or
    their nearest reaches :data:`NEAR`)."""
    lo, hi = 1e-3, max(start, 1e-3)
    while not _fits(P, target + hi * view, target):
        hi *= 2
    for _ in range(steps):  # bisection: the bracket shrinks 2^steps times
        mid = (lo + hi) / 2
        lo, hi = (lo, mid) if _fits(P, target + mid * view, target) else (mid, hi)
    return hi
