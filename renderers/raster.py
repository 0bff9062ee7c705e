"""An exact-geometry CPU rasteriser for the scenes stereotrack draws with flat shading: spheres,
thin discs and boxes of one colour each over a plain or vertex-coloured background plane.

Each pixel a solid's projected bounds touch is sampled on a 4 × 4 grid (one sample at its centre
when multisampling is off); each sample's ray is intersected with every solid whose bounds hold the
pixel (Glassner, *An Introduction to Ray Tracing*, 1989, ch. 2: the ray–sphere quadratic, the
slab test for boxes, cylinder walls and caps) and takes the nearest one's colour, or the
background's at the pixel centre (as a multisampled rasteriser shades it), and the pixel is the
samples' mean. The background is the same for every frame of a static camera, so it is drawn once:
the ray through each pixel centre meets the plane, whose two triangles per grid cell interpolate
the vertex colours linearly on the plane (what OpenGL's perspective-correct interpolation gives).

Solids are exact here (a true sphere and circle where pyrender draws an icosphere of 642 vertices
and a 48-gon), and coverage is 16 samples against pyrender's 4: blob centres agree within a few
hundredths of a pixel (tests/renderers/test_raster.py). pyrender stays the reference, and draws
lit shading and scenes with distractors (whose segmentation render decides marker visibility).
"""

from __future__ import annotations

import numpy as np

from renderers.scene import ScenePoses

SPHERE, CYLINDER, BOX = 0, 1, 2
_KINDS = {"sphere": SPHERE, "cylinder": CYLINDER, "box": BOX}
#: samples per side of a pixel's grid when multisampling is on
GRID = 4
#: pyrender's near plane (m): nothing nearer the camera is drawn
ZNEAR = 0.01


class AnalyticScene(ScenePoses):
    """The scene drawn by :func:`renderers._raster_kernel.draw` (numba): ``render`` takes no GL renderer (pass None)."""

    def __init__(self, scenario, rig, truth) -> None:
        super().__init__(scenario, rig, truth)
        self.kinds = np.array([_KINDS[s.kind] for s in self.shapes], np.int64)
        self.colors = np.array([s.color for s in self.shapes], np.float64).reshape(-1, 3)
        self.samples = GRID if scenario.render.multisample > 0 else 1
        self._backgrounds: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def render(self, renderer, camera_index: int) -> np.ndarray:
        """RGB uint8 pinhole image of the current pose from camera ``camera_index`` (at its
        :class:`RenderView`'s size; ``renderer`` is unused)."""
        from renderers._raster_kernel import draw

        bg, bg_u8, depth = self._background(camera_index)
        K = self.views[camera_index].K
        geo, boxes = self._solids(camera_index, K, bg.shape[1], bg.shape[0])
        img = bg_u8.copy()
        if len(geo):
            done = np.zeros(depth.shape, np.uint8)
            lens = (float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]))
            draw(img, bg, depth, (self.kinds, geo, self.colors, boxes), lens, self.samples, done)
        return img

    def _solids(self, camera_index: int, K: np.ndarray, w: int, h: int) -> tuple[np.ndarray, np.ndarray]:
        """Each solid in the camera's frame (:func:`~renderers._raster_kernel.draw`'s rows) and its pixel bounds (u0, v0,
        u1, v1; u0 > u1 when it is out of view)."""
        cam = self.rig.cameras[camera_index]
        n = len(self.shapes)
        geo, boxes = np.zeros((n, 16)), np.zeros((n, 4), np.int64)
        for i, (shape, pose) in enumerate(zip(self.shapes, self.poses, strict=True)):
            c = cam.R @ pose[:3, 3] + cam.t
            R = cam.R @ pose[:3, :3]
            geo[i, :3] = c
            if shape.kind == "sphere":
                geo[i, 3] = shape.size[0]
                R, e = np.eye(3), np.full(3, shape.size[0])
            elif shape.kind == "cylinder":
                geo[i, 3:6], geo[i, 6], geo[i, 7] = R[:, 2], shape.size[0], shape.size[1] / 2
                e = np.array([shape.size[0], shape.size[0], shape.size[1] / 2])
            else:
                e = np.asarray(shape.size) / 2
                geo[i, 3:12], geo[i, 12:15] = R.T.ravel(), e
            boxes[i] = _bounds(c + (_CORNERS * e) @ R.T, K, w, h)
        return geo, boxes

    def _background(self, camera_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The camera's background image (float, and rounded to uint8) and its depth per pixel
        (inf where nothing but the background colour is seen); computed once per camera."""
        if camera_index not in self._backgrounds:
            self._backgrounds[camera_index] = _background_image(self, camera_index)
        return self._backgrounds[camera_index]


#: the corners of a cube of half-side 1
_CORNERS = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)


def _bounds(corners: np.ndarray, K: np.ndarray, w: int, h: int) -> np.ndarray:
    """Pixel bounds (one pixel of margin) of a solid inside the box of these ``corners`` (camera
    frame): their projections' extent (a convex solid in front of the camera projects inside the
    hull of its box's corners); all of the image when the box crosses the near plane."""
    z = corners[:, 2]
    if z.max() <= ZNEAR:
        return np.array([1, 1, 0, 0])
    if z.min() <= ZNEAR:
        return np.array([0, 0, w - 1, h - 1])
    u = K[0, 0] * corners[:, 0] / z + K[0, 2]
    v = K[1, 1] * corners[:, 1] / z + K[1, 2]
    lo = np.floor([u.min() - 1, v.min() - 1])
    hi = np.ceil([u.max() + 1, v.max() + 1])
    return np.array([max(lo[0], 0), max(lo[1], 0), min(hi[0], w - 1), min(hi[1], h - 1)], np.int64)


def _background_image(scene: ScenePoses, camera_index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """See :meth:`AnalyticScene._background`: each pixel centre's ray meets the background plane
    z = D (world), whose grid cell's triangle interpolates its three vertex colours."""
    view, cam = scene.views[camera_index], scene.rig.cameras[camera_index]
    w, h = view.size
    K = view.K
    rgb = np.asarray(scene.scenario.render.background_color, np.float64)
    bg = np.broadcast_to(rgb, (h, w, 3)).copy()
    depth = np.full((h, w), np.inf)
    grid = scene.background_grid()
    if grid is not None:
        xs, ys, cols = grid
        u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
        d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # camera frame, z = 1
        world = d @ cam.R  # Rᵀ d per pixel
        C = cam.center
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (scene.scenario.render.background_distance - C[2]) / world[..., 2]
        gx = (C[0] + t * world[..., 0] - xs[0]) / (xs[1] - xs[0])
        gy = (C[1] + t * world[..., 1] - ys[0]) / (ys[1] - ys[0])
        inside = (t > ZNEAR) & (gx >= 0) & (gx <= len(xs) - 1) & (gy >= 0) & (gy <= len(ys) - 1)
        bg[inside] = _interpolate(cols.astype(np.float64), gx[inside], gy[inside])
        depth[inside] = t[inside]
    return bg, np.floor(bg + 0.5).astype(np.uint8), depth


def _interpolate(cols: np.ndarray, gx: np.ndarray, gy: np.ndarray) -> np.ndarray:
    """Vertex colours at grid coordinates: cell (ix, iy) is split along the diagonal from (ix+1, iy)
    to (ix, iy+1); each triangle interpolates its corners linearly."""
    ix = np.minimum(gx.astype(np.int64), cols.shape[1] - 2)
    iy = np.minimum(gy.astype(np.int64), cols.shape[0] - 2)
    fx, fy = (gx - ix)[:, None], (gy - iy)[:, None]
    a, b = cols[iy, ix], cols[iy, ix + 1]
    c, d = cols[iy + 1, ix], cols[iy + 1, ix + 1]
    upper = fx + fy <= 1
    return np.where(upper, a + fx * (b - a) + fy * (c - a), d + (1 - fx) * (c - d) + (1 - fy) * (b - d))
