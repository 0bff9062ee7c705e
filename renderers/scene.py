"""The pyrender scene of a scenario: sphere markers, the four-point plate, a textured background,
distractors, and one camera node per rig camera. Poses come from the one camera model."""

from __future__ import annotations

import os

import numpy as np

from pipeline.camera import StereoRig
from pipeline.errors import RenderBackendError
from renderers.motion import Truth, distractor_positions
from renderers.scenario import Scenario

GL_HELP = (
    "install Mesa's EGL (Debian/Ubuntu: apt-get install libegl1 libgl1-mesa-dri) and set "
    "PYOPENGL_PLATFORM=egl, or install OSMesa (apt-get install libosmesa6) and set PYOPENGL_PLATFORM=osmesa"
)


def ensure_gl_platform() -> str:
    """Default PyOpenGL to headless EGL (must happen before pyrender/OpenGL is imported)."""
    return os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def create_offscreen_renderer(width: int, height: int):  # -> pyrender.OffscreenRenderer
    """An off-screen renderer, or one clear :class:`RenderBackendError` saying how to get EGL/OSMesa."""
    platform = ensure_gl_platform()
    try:
        import pyrender

        return pyrender.OffscreenRenderer(width, height)
    except Exception as exc:
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise RenderBackendError(
            f"no OpenGL backend for off-screen rendering (PYOPENGL_PLATFORM={platform}: {reason}); {GL_HELP}"
        ) from None


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


def _material(rgb: tuple[int, int, int]):
    import pyrender

    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[c / 255.0 for c in rgb] + [1.0], metallicFactor=0.0, roughnessFactor=0.9
    )


class StereoScene:
    """All geometry of a scenario, posed per frame; renders either camera of the rig."""

    def __init__(self, scenario: Scenario, rig: StereoRig, truth: Truth) -> None:
        ensure_gl_platform()
        import pyrender
        import trimesh

        self.scenario, self.rig, self.truth = scenario, rig, truth
        rs = scenario.render
        self.flat = rs.shading == "flat"
        self.scene = pyrender.Scene(bg_color=[*(c / 255 for c in rs.background_color), 1.0], ambient_light=[0.35] * 3)
        self._marker_nodes = []
        names = scenario.marker_colors()
        for i, name in enumerate(truth.names):
            color = names[name]
            r = float(truth.radii[i])
            if np.all(np.isfinite(truth.normals[0, i])):
                tm = trimesh.creation.cylinder(radius=r, height=0.001, sections=48)
            else:
                tm = trimesh.creation.icosphere(subdivisions=3, radius=r)
            mesh = pyrender.Mesh.from_trimesh(tm, material=_material(color), smooth=not self.flat)
            self._marker_nodes.append(self.scene.add(mesh, name=name))
        self._plates = []
        for obj, tgt in zip([o for o in scenario.objects if o.is_target], truth.targets, strict=True):
            side = 2.8 * tgt.radius
            plate = trimesh.creation.box(extents=[side, side, 0.004])
            node = self.scene.add(pyrender.Mesh.from_trimesh(plate, material=_material(obj.plate_color)))
            self._plates.append((node, tgt))
        self._distractors = []
        dpos = distractor_positions(scenario)
        for j, d in enumerate(scenario.distractors):
            tm = trimesh.creation.box(extents=[d.size] * 3) if d.shape == "cube" else trimesh.creation.icosphere(3, d.size / 2)
            node = self.scene.add(pyrender.Mesh.from_trimesh(tm, material=_material(d.color)))
            self._distractors.append((node, dpos[:, j]))
        if rs.background == "textured":
            self.scene.add(self._background_mesh(), pose=np.eye(4))
        self._camera_nodes = []
        for cam in rig.cameras:
            fx, fy, cx, cy = cam.gl_intrinsics()
            node = self.scene.add(
                pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=0.01, zfar=rs.background_distance * 4),
                pose=cam.gl_pose(),
            )
            self._camera_nodes.append(node)
        if not self.flat:
            light = pyrender.DirectionalLight(color=np.ones(3), intensity=2.5)
            light_pose = _pose(_frame_from_normal(np.array([0.3, 0.5, 1.0])), np.zeros(3)) @ np.diag([1, -1, -1, 1])
            self.scene.add(light, pose=light_pose)

    def _background_mesh(self):
        """A large plane at ``background_distance`` with a smooth low-saturation grey texture
        (vertex colours: cheap and seeded), covering both cameras' views."""
        import pyrender
        import trimesh

        rs = self.scenario.render
        D = rs.background_distance
        w, h = self.rig.image_size
        K = self.rig.left.K
        half_w = D * max(K[0, 2], w - K[0, 2]) / K[0, 0] * 1.8 + self.rig.baseline + D * 0.5
        half_h = D * max(K[1, 2], h - K[1, 2]) / K[1, 1] * 1.8
        nx, ny = 64, 48
        xs, ys = np.linspace(-half_w, half_w, nx), np.linspace(-half_h, half_h, ny)
        X, Y = np.meshgrid(xs, ys)
        verts = np.column_stack([X.ravel() + self.rig.baseline / 2, Y.ravel(), np.full(X.size, D)])
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        faces = np.concatenate([np.column_stack([a, c, b]), np.column_stack([b, c, d])])
        rng = np.random.default_rng([self.scenario.seed, 10_000])
        base = np.array(rs.background_color, float)
        shade = 0.55 + 0.9 * rng.random(len(verts))
        cols = np.clip(base[None, :] * shade[:, None], 0, 255)
        rgba = np.column_stack([cols, np.full(len(verts), 255)]).astype(np.uint8)
        tm = trimesh.Trimesh(verts, faces, vertex_colors=rgba, process=False)
        return pyrender.Mesh.from_trimesh(tm, smooth=True)

    def set_frame(self, k: int) -> None:
        """Pose every object for frame ``k``."""
        pos, nrm = self.truth.positions[k], self.truth.normals[k]
        for i, node in enumerate(self._marker_nodes):
            if np.all(np.isfinite(nrm[i])):
                self.scene.set_pose(node, _pose(_frame_from_normal(nrm[i]), pos[i] + 0.0005 * nrm[i]))
            else:
                self.scene.set_pose(node, _pose(np.eye(3), pos[i]))
        for node, tgt in self._plates:
            n = tgt.normal[k]
            b = np.array([np.cos(tgt.axis_angle), np.sin(tgt.axis_angle), 0.0])
            self.scene.set_pose(node, _pose(_frame_from_normal(n, b), tgt.center[k] - 0.0025 * n))
        for node, p in self._distractors:
            self.scene.set_pose(node, _pose(np.eye(3), p[k]))

    def render(self, renderer, camera_index: int) -> np.ndarray:
        """RGB uint8 image (H×W×3) of the current frame from camera ``camera_index``."""
        import pyrender

        self.scene.main_camera_node = self._camera_nodes[camera_index]
        flags = pyrender.RenderFlags.FLAT if self.flat else pyrender.RenderFlags.NONE
        color, _ = renderer.render(self.scene, flags=flags)
        return color
