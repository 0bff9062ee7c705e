"""The solids of a scenario (sphere markers, the four-point plate, distractors), posed per frame or
per camera time, over a plain or textured background; and the pyrender scene that draws them (one
node per solid, one camera node per rig camera). Poses come from the one camera model."""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from pipeline.core.camera import Camera, StereoRig
from pipeline.core.errors import RenderBackendError, first_line
from pipeline.core.rig import Rig
from renderers.motion import Truth, distractor_positions
from renderers.scenario import Scenario

GL_HELP = (
    "install Mesa's EGL (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri) and set "
    "PYOPENGL_PLATFORM=egl, or install OSMesa (apt-get install libosmesa6) and set PYOPENGL_PLATFORM=osmesa"
)


def ensure_gl_platform() -> str:
    """Default PyOpenGL to headless EGL (must happen before pyrender/OpenGL is imported). Under EGL,
    pyglet (which pyrender imports for its viewer) is told it is headless too: otherwise it looks
    for X11 libraries (libXrender), which a GPU server without a desktop lacks."""
    platform = os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    if platform == "egl":
        os.environ.setdefault("PYGLET_HEADLESS", "true")
    return platform


def create_offscreen_renderer(width: int, height: int, multisample: int = 4):  # -> pyrender.OffscreenRenderer
    """An off-screen renderer that reads back only the colour image (pyrender also reads, converts
    and returns the depth buffer, which nothing here uses: 37 % of a render's CPU time on llvmpipe),
    rendering with ``multisample`` samples per pixel (pyrender's fixed 4; 0 turns multisampling
    off); or one clear :class:`RenderBackendError` saying how to get EGL/OSMesa."""
    platform = ensure_gl_platform()
    try:
        import pyrender

        r = pyrender.OffscreenRenderer(width, height)
    except Exception as exc:
        reason = first_line(exc)
        raise RenderBackendError(
            f"no OpenGL backend for off-screen rendering (PYOPENGL_PLATFORM={platform}: {reason}); {GL_HELP}"
        ) from None
    _read_colour_only(r._renderer)
    set_multisample(r, multisample)
    from OpenGL import GL

    name = (GL.glGetString(GL.GL_RENDERER) or b"").decode(errors="replace").lower()
    r.software = any(s in name for s in ("llvmpipe", "softpipe", "swrast"))  # Mesa's CPU rasterisers
    return r


#: samples per pixel of the multisampled framebuffer pyrender creates next (see set_multisample)
_SAMPLES = [4]


def set_multisample(renderer, samples: int) -> None:
    """Render with ``samples`` per pixel from now on (0: no multisampling). pyrender hard-codes 4
    in its framebuffer; the framebuffer is rebuilt when the count changes."""
    import pyrender.renderer as pr

    if not getattr(pr, "_stereotrack_samples", False):
        real = pr.glRenderbufferStorageMultisample
        pr.glRenderbufferStorageMultisample = lambda target, _n, fmt, w, h: real(target, _SAMPLES[0], fmt, w, h)
        pr._stereotrack_samples = True
    if getattr(renderer, "_samples", None) != samples:
        _SAMPLES[0] = int(samples)
        renderer._renderer._delete_main_framebuffer()
        renderer._samples = int(samples)


def _read_colour_only(inner) -> None:
    """Replace pyrender 0.1.45's framebuffer read-back by one that blits and reads the colour
    image only (depth is returned as None); depth-only renders keep pyrender's own."""
    import types

    from OpenGL import GL

    original = inner._read_main_framebuffer

    def read(self, scene, flags):
        import pyrender

        if flags & pyrender.RenderFlags.DEPTH_ONLY:
            return original(scene, flags)
        w, h = self._main_fb_dims
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb_ms)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._main_fb)
        GL.glBlitFramebuffer(0, 0, w, h, 0, 0, w, h, GL.GL_COLOR_BUFFER_BIT, GL.GL_LINEAR)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._main_fb)
        rgba = bool(flags & pyrender.RenderFlags.RGBA)
        buf = GL.glReadPixels(0, 0, w, h, GL.GL_RGBA if rgba else GL.GL_RGB, GL.GL_UNSIGNED_BYTE)
        return np.flip(np.frombuffer(buf, dtype=np.uint8).reshape(h, w, 4 if rgba else 3), axis=0), None

    inner._read_main_framebuffer = types.MethodType(read, inner)


@dataclass
class RenderView:
    """How one camera is rendered: a pinhole camera ``K`` of ``size`` (the camera's own, or with a
    margin when its lens distorts), and the remap (``cv2.remap`` maps) that bends that pinhole image
    into the distorted one the camera records."""

    K: np.ndarray
    size: tuple[int, int]
    maps: tuple[np.ndarray, np.ndarray] | None = None

    def finish(self, img: np.ndarray, nearest: bool = False) -> np.ndarray:
        """The pinhole render as the camera records it (the identity without distortion)."""
        if self.maps is None:
            return img
        import cv2

        return cv2.remap(img, *self.maps, cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


#: The largest render, per side, that a distorted camera's margin may grow to (× its image size).
MAX_MARGIN = 2.0
#: The most pixels a distorted camera's pinhole render may have (× its image's): a lens whose
#: undistorted frame is larger is rendered with a proportionally shorter focal length (k1 = −0.3
#: at 640×480: 0.91 of the native resolution at the centre), then remapped.
MAX_RENDER_AREA = 1.15

_VIEWS: dict[bytes, RenderView] = {}


def render_view(cam: Camera, image_size: tuple[int, int]) -> RenderView:
    """The view of ``cam``: every pixel of its distorted image, undistorted onto the pinhole image
    plane (``cv2.undistortPoints`` with ``P = K``), sets the margin the pinhole render needs and the
    remap from it; a lens without distortion renders as it is. Computed once per lens and size."""
    if not np.any(cam.D):
        return RenderView(cam.K, image_size)
    key = cam.K.tobytes() + cam.D.tobytes() + bytes(str(image_size), "ascii")
    if key not in _VIEWS:
        _VIEWS[key] = _distorted_view(cam, image_size)
    return _VIEWS[key]


def _distorted_view(cam: Camera, image_size: tuple[int, int]) -> RenderView:
    w, h = image_size
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    und = cam.undistort(np.stack([u.ravel(), v.ravel()], -1)).reshape(h, w, 2)
    lim = np.array([w, h]) * MAX_MARGIN
    und = np.clip(np.nan_to_num(und, nan=-1e9), -lim, np.array([w, h]) + lim)
    lo, hi = und.reshape(-1, 2).min(axis=0) - 2, und.reshape(-1, 2).max(axis=0) + 2
    s = min(1.0, float(np.sqrt(MAX_RENDER_AREA * w * h / np.prod(hi - lo))))
    # the render camera: the pinhole plane scaled by s about the principal point, shifted to the margin
    c = cam.K[:2, 2]
    lo_s, hi_s = c + s * (lo - c), c + s * (hi - c)
    K = cam.K.copy()
    K[:2, :2] *= s
    K[:2, 2] = c - np.floor(lo_s)
    maps = tuple((c[i] + s * (und[..., i] - c[i]) - np.floor(lo_s[i])).astype(np.float32) for i in range(2))
    size = (int(np.ceil(hi_s[0]) - np.floor(lo_s[0])) + 1, int(np.ceil(hi_s[1]) - np.floor(lo_s[1])) + 1)
    return RenderView(K, size, (maps[0], maps[1]))


def _frame_from_normal(n: np.ndarray, b: np.ndarray | None = None) -> np.ndarray:
    """Rotation whose z column is ``n`` (and x column ``b`` when given and orthogonal)."""
    n = n / np.linalg.norm(n)
    if b is None:
        b = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    b = b - n * (b @ n)
    b /= np.linalg.norm(b)
    return np.column_stack([b, np.cross(n, b), n])


def _pose(R: np.ndarray, p: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = p
    return T


def _material(rgb: tuple[int, int, int], roughness: float = 0.9):
    import pyrender

    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[c / 255.0 for c in rgb] + [1.0], metallicFactor=0.0, roughnessFactor=roughness
    )


@dataclass(frozen=True)
class Shape:
    """One solid of a scene in its own frame: a ``sphere`` (``size``: radius), a thin ``cylinder``
    along z (radius, height: a flat marker disc) or a ``box`` (x, y, z extents), of one colour."""

    kind: str
    size: tuple[float, ...]
    color: tuple[int, int, int]
    roughness: float = 0.9
    smooth: bool = True


#: a flat marker's disc: this thick, lifted by half of it off the plate's face
DISC_HEIGHT = 0.001
#: the four-point target's plate: this thick, its face 0.5 mm behind the markers' centres
PLATE_THICKNESS = 0.004


class ScenePoses:
    """All solids of a scenario (markers, the four-point plates, distractors; :attr:`shapes`) and
    their poses per frame or per camera time (:attr:`poses`, one 4×4 object→world matrix each), with
    each camera's :class:`RenderView` and the background: what every rasteriser draws from."""

    def __init__(self, scenario: Scenario, rig: StereoRig | Rig, truth: Truth) -> None:
        self.scenario, self.rig, self.truth = scenario, rig, truth
        rs = scenario.render
        self.flat = rs.shading == "flat"
        names = scenario.marker_colors()
        rough = {n: o.roughness for o in scenario.objects for n in o.marker_names()}
        shapes = []
        for i, name in enumerate(truth.names):
            r = float(truth.radii[i])
            disc = bool(np.all(np.isfinite(truth.normals[0, i])))
            shapes.append(Shape("cylinder" if disc else "sphere", (r, DISC_HEIGHT) if disc else (r,), names[name],
                                rough[name], smooth=not self.flat))
        self.n_markers = len(shapes)
        for obj, tgt in zip([o for o in scenario.objects if o.is_target], truth.targets, strict=True):
            side = 2.8 * tgt.radius
            shapes.append(Shape("box", (side, side, PLATE_THICKNESS), obj.plate_color))
        self._distractors = distractor_positions(scenario)
        for d in scenario.distractors:
            sphere = d.shape == "sphere"
            size = (d.size / 2,) if sphere else tuple(d.extents) if d.extents is not None else (d.size,) * 3
            shapes.append(Shape("sphere" if sphere else "box", size, d.color, d.roughness,
                                smooth=sphere and not self.flat))
        self.shapes: list[Shape] = shapes
        self.poses = np.tile(np.eye(4), (len(shapes), 1, 1))
        self.views = [render_view(cam, size) for cam, size in zip(rig.cameras, rig.sizes, strict=True)]

    def background_grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The textured background (None when plain): a plane at ``background_distance`` covering
        every camera's view, a grid of 48 × 64 vertices (x and y in the world, ascending) with
        seeded low-saturation grey colours (RGB uint8, 48 × 64 × 3), two triangles per cell."""
        rs = self.scenario.render
        if rs.background != "textured":
            return None
        D = rs.background_distance
        w, h = self.rig.image_size
        K = self.rig.cameras[0].K
        half_w = D * max(K[0, 2], w - K[0, 2]) / K[0, 0] * 1.8 + self.rig.baseline + D * 0.5
        half_h = D * max(K[1, 2], h - K[1, 2]) / K[1, 1] * 1.8
        nx, ny = 64, 48
        xs, ys = np.linspace(-half_w, half_w, nx) + self.rig.baseline / 2, np.linspace(-half_h, half_h, ny)
        rng = np.random.default_rng([self.scenario.seed, 10_000])
        base = np.array(rs.background_color, float)
        shade = 0.55 + 0.9 * rng.random(nx * ny)
        cols = np.clip(base[None, :] * shade[:, None], 0, 255).astype(np.uint8)
        return xs, ys, cols.reshape(ny, nx, 3)

    def set_frame(self, k: int) -> None:
        """Pose every object for frame ``k`` (an ideal rig: every camera at ``k/fps``)."""
        self._pose(self.truth.positions[k], self.truth.normals[k],
                   [(tgt.center[k], tgt.normal[k]) for tgt in self.truth.targets], list(self._distractors[k]))

    def set_time(self, camera: int, t0: float) -> None:
        """Pose every object as ``camera`` sees it in a frame whose row 0 is exposed at ``t0``: with
        a rolling shutter each moving object at the time of the row that images its centre (the
        skew across one small object is left out)."""
        from renderers.truth import seen_at

        cam, ld, h = self.rig.cameras[camera], self.scenario.rig.line_delay_s, self.rig.sizes[camera][1]
        n = self.n_markers
        pos, nrm = np.empty((n, 3)), np.empty((n, 3))
        for i in range(n):
            t = seen_at(cam, self.truth, i, np.array([t0]), ld, h)
            p, _, nn = self.truth.at(t, [i])
            pos[i], nrm[i] = p[0, 0], nn[0, 0]
        plates = []
        for tp in self.truth.target_paths:
            t = self._row_time(cam, lambda t, tp=tp: tp.points_at(t)[3], t0, h)
            _, _, normal, center, _ = tp.points_at(t)
            plates.append((center[0], normal[0]))
        dist = [distractor_positions(self.scenario, self._row_time(
            cam, lambda t, j=j: distractor_positions(self.scenario, t)[:, j], t0, h))[0, j]
            for j in range(len(self.scenario.distractors))]
        self._pose(pos, nrm, plates, dist)

    def _row_time(self, cam: Camera, where, t0: float, h: int) -> np.ndarray:
        """When the row imaging ``where(t)`` (a centre) is exposed, from ``t0`` (fixed point)."""
        ld = self.scenario.rig.line_delay_s
        t = np.array([t0])
        for _ in range(4 if ld > 0 else 0):
            v = cam.project_distorted(where(t))[:, 1]
            t = t0 + np.clip(np.nan_to_num(v, nan=0.0), 0.0, h - 1.0) * ld
        return t

    def _pose(self, pos: np.ndarray, nrm: np.ndarray, plates: list, distractors: list) -> None:
        poses = self.poses
        for i in range(self.n_markers):
            if np.all(np.isfinite(nrm[i])):
                poses[i] = _pose(_frame_from_normal(nrm[i]), pos[i] + 0.5 * DISC_HEIGHT * nrm[i])
            else:
                poses[i] = _pose(np.eye(3), pos[i])
        j = self.n_markers
        for tgt, (center, n) in zip(self.truth.targets, plates, strict=True):
            b = np.array([np.cos(tgt.axis_angle), np.sin(tgt.axis_angle), 0.0])
            poses[j] = _pose(_frame_from_normal(n, b), center - 0.5 * (PLATE_THICKNESS + DISC_HEIGHT) * n)
            j += 1
        for p in distractors:
            poses[j] = _pose(np.eye(3), p)
            j += 1
        self._placed()

    def _placed(self) -> None:
        """Called after :attr:`poses` changed (a rasteriser with a scene graph moves its nodes)."""


class StereoScene(ScenePoses):
    """The scene as pyrender draws it (the reference rasteriser, and the one for lit shading and
    distractors): one mesh node per solid, a vertex-coloured background mesh, one camera node per
    rig camera; renders either camera through its :class:`RenderView`."""

    def __init__(self, scenario: Scenario, rig: StereoRig | Rig, truth: Truth) -> None:
        ensure_gl_platform()
        import pyrender

        super().__init__(scenario, rig, truth)
        rs = scenario.render
        self.scene = pyrender.Scene(bg_color=[*(c / 255 for c in rs.background_color), 1.0], ambient_light=[0.35] * 3)
        self._nodes = [self.scene.add(_mesh(s), name=name)
                       for s, name in zip(self.shapes, [*truth.names, *[None] * (len(self.shapes) - self.n_markers)],
                                          strict=True)]
        self._marker_nodes = self._nodes[: self.n_markers]
        grid = self.background_grid()
        if grid is not None:
            self.scene.add(_background_mesh(*grid, rs.background_distance), pose=np.eye(4))
        self._camera_nodes = []
        for cam, view in zip(rig.cameras, self.views, strict=True):
            fx, fy, cx, cy = Camera(view.K, cam.R, cam.t).gl_intrinsics()
            node = self.scene.add(
                pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=0.01, zfar=rs.background_distance * 4),
                pose=cam.gl_pose(),
            )
            self._camera_nodes.append(node)
        if not self.flat:
            light = pyrender.DirectionalLight(color=np.ones(3), intensity=2.5)
            light_pose = _pose(_frame_from_normal(np.array([0.3, 0.5, 1.0])), np.zeros(3)) @ np.diag([1, -1, -1, 1])
            self.scene.add(light, pose=light_pose)
        # segmentation: marker i drawn in colour i + 1, everything else black (and still occluding)
        self._seg_map = {n: [0, 0, 0] for n in self.scene.mesh_nodes}
        self._seg_map.update({n: [i + 1, 0, 0] for i, n in enumerate(self._marker_nodes)})

    def _placed(self) -> None:
        for node, pose in zip(self._nodes, self.poses, strict=True):
            self.scene.set_pose(node, pose)

    def render(self, renderer, camera_index: int) -> np.ndarray:
        """RGB uint8 pinhole image of the current pose from camera ``camera_index`` (at its
        :class:`RenderView`'s size: :meth:`RenderView.finish` makes it the camera's image)."""
        import pyrender

        self._aim(renderer, camera_index)
        flags = pyrender.RenderFlags.FLAT if self.flat else pyrender.RenderFlags.NONE
        color, _ = renderer.render(self.scene, flags=flags)
        return color

    def _aim(self, renderer, camera_index: int) -> None:
        """Render from camera ``camera_index``, at its view's size (one GL context serves every
        size: pyrender resizes its framebuffers when the viewport changes)."""
        self.scene.main_camera_node = self._camera_nodes[camera_index]
        renderer.viewport_width, renderer.viewport_height = self.views[camera_index].size

    def marker_pixels(self, renderer, camera_index: int) -> np.ndarray:
        """How many pixels of each marker camera ``camera_index`` sees in the current pose (a
        segmentation render: occluders hide, the frame's edge cuts), in the camera's own image."""
        import pyrender

        self._aim(renderer, camera_index)
        seg, _ = renderer.render(self.scene, flags=pyrender.RenderFlags.SEG, seg_node_map=self._seg_map)
        ids = self.views[camera_index].finish(np.ascontiguousarray(seg[..., 0]), nearest=True)
        return np.bincount(ids.ravel(), minlength=len(self._marker_nodes) + 1)[1 : len(self._marker_nodes) + 1]


def _mesh(shape: Shape):
    """The pyrender mesh of a solid (an icosphere of 642 vertices, a 48-sided disc, a box)."""
    import pyrender
    import trimesh

    if shape.kind == "sphere":
        tm = trimesh.creation.icosphere(subdivisions=3, radius=shape.size[0])
    elif shape.kind == "cylinder":
        tm = trimesh.creation.cylinder(radius=shape.size[0], height=shape.size[1], sections=48)
    else:
        tm = trimesh.creation.box(extents=list(shape.size))
    return pyrender.Mesh.from_trimesh(tm, material=_material(shape.color, shape.roughness), smooth=shape.smooth)


def _background_mesh(xs: np.ndarray, ys: np.ndarray, cols: np.ndarray, distance: float):
    """The background grid as a vertex-coloured pyrender mesh (colours interpolated smoothly)."""
    import pyrender
    import trimesh

    X, Y = np.meshgrid(xs, ys)
    verts = np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, distance)])
    ny, nx = X.shape
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
    rgba = np.column_stack([cols.reshape(-1, 3), np.full(nx * ny, 255, np.uint8)])
    tm = trimesh.Trimesh(verts, faces, vertex_colors=rgba, process=False)
    return pyrender.Mesh.from_trimesh(tm, smooth=True)
