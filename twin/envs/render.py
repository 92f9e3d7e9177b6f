"""Offscreen MuJoCo pictures of one environment's state: the deformed skin, the indenter, the force arrow.

`SkinRenderer` builds a small MuJoCo model (no simulation, drawing only) of the BioTac frame (x distal,
-z the ventral pad; metres): the FE skin mid-surface as one mesh geom whose vertex positions and normals
are overwritten and re-uploaded to the GL context for every frame (so the picture shows the FE's
deformation), the rigid core under it, and the indenter (translucent) as a mocap body at its pose. The
force of the indenter on the skin is drawn as an arrow along it ending at the tip, `FORCE_ARROW_M_PER_N`
long per newton up to 15 mm. Any arrow along the force that ends at the tip lies inside the indenter
(whose translucent colour blends over it) or inside the opaque skin, so the arrow is drawn in a second
pass over the finished picture: it is seen wherever it is. The camera looks at the indenter tip from below the pad,
so the tip is at the frame's centre. `render` returns an (H, W, 3) uint8 frame.

OpenGL: MuJoCo draws offscreen through an EGL or OSMesa context (no display needed). The backend named
by the MUJOCO_GL environment variable is used when set; otherwise EGL, then OSMesa, is tried. When none
opens, `SkinRenderer` raises a one-line RuntimeError naming MUJOCO_GL.
"""

from __future__ import annotations

import importlib
import os
from typing import Any

import mujoco
import numpy as np

from assets.biotac import vertex_normals
from assets.indenters import get_indenter

FORCE_ARROW_M_PER_N = 3e-3
"""Length of the force arrow per newton (m/N), up to `FORCE_ARROW_MAX_M`."""
FORCE_ARROW_MAX_M = 15e-3
"""Longest force arrow drawn (m): a larger force keeps this length (the camera is 45 mm away)."""
INDENTER_MESH_EDGE = 1e-3
"""Largest edge (m) of the indenter mesh drawn."""
OFFSCREEN_BACKENDS = ("egl", "osmesa")
"""MuJoCo's offscreen OpenGL backends, tried in this order when MUJOCO_GL is not set."""
SKIN_RGBA = (0.85, 0.68, 0.55, 1.0)
CORE_RGBA = (0.35, 0.35, 0.4, 1.0)
INDENTER_RGBA = (0.6, 0.65, 0.8, 0.45)
FORCE_RGBA = np.array([0.95, 0.15, 0.15, 1.0], dtype=np.float32)
CAMERA_DISTANCE_M = 0.045
CAMERA_AZIMUTH_DEG = 135.0
CAMERA_ELEVATION_DEG = 35.0
"""The free camera: distance (m) from the tip it looks at, azimuth and elevation (deg; > 0: from below)."""


def open_gl_context(width: int, height: int) -> Any:
    """A current offscreen GL context of at least `width` x `height` pixels (module docstring for the
    backend choice); a one-line RuntimeError naming MUJOCO_GL when none opens."""
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    backends = (chosen,) if chosen else OFFSCREEN_BACKENDS
    failures = []
    for backend in backends:
        try:
            context = importlib.import_module(f"mujoco.{backend}").GLContext(width, height)
            context.make_current()
            return context
        except Exception as error:  # noqa: BLE001 (any backend failure means: try the next one)
            failures.append(f"{backend}: {type(error).__name__}: {str(error).splitlines()[0] if str(error) else ''}")
    raise RuntimeError(
        "render_mode 'rgb_array' needs an offscreen OpenGL backend; set MUJOCO_GL=egl (or osmesa) to one "
        f"this machine has (tried {'; '.join(failures)})"
    )


def _rotation_quat(rotation: np.ndarray) -> np.ndarray:
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(rotation, dtype=float).ravel())
    return quat


def build_model(
    reference: np.ndarray,
    triangles: np.ndarray,
    core: tuple[np.ndarray, np.ndarray],
    indenter: str,
    width: int,
    height: int,
) -> mujoco.MjModel:
    """The drawing model: skin mesh `reference` (V, 3) m / `triangles` (T, 3), core (vertices, triangles),
    the indenter's mesh on a mocap body, an offscreen buffer of `width` x `height` pixels."""
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = width, height
    spec.visual.headlight.ambient = (0.35, 0.35, 0.35)
    tool = spec.worldbody.add_body(name="indenter", mocap=True)
    shape = get_indenter(indenter).mesh(INDENTER_MESH_EDGE)
    drawn = (
        ("skin", spec.worldbody, reference, triangles, SKIN_RGBA),
        ("core", spec.worldbody, *core, CORE_RGBA),
        ("indenter", tool, shape.vertices, shape.faces, INDENTER_RGBA),
    )
    for name, body, vertices, faces, rgba in drawn:
        mesh = spec.add_mesh(name=name, uservert=np.ravel(vertices).tolist(), userface=np.ravel(faces).tolist())
        mesh.inertia = mujoco.mjtMeshInertia.mjMESH_INERTIA_SHELL  # open surfaces: no solid volume needed
        geom = body.add_geom(name=name, type=mujoco.mjtGeom.mjGEOM_MESH, meshname=name, rgba=rgba)
        geom.contype = geom.conaffinity = 0  # drawn only
    spec.worldbody.add_light(pos=(0.0, 0.0, -0.1), dir=(0.0, 0.0, 1.0), diffuse=(0.5, 0.5, 0.5))
    return spec.compile()


class SkinRenderer:
    """Draws states of one BioTac skin (see the module docstring) into (height, width, 3) uint8 frames.

    reference (V, 3) m and triangles (T, 3): the inflated skin mid-surface; core: the rigid core's
    (vertices (C, 3) m, triangles); indenter: its name (assets.indenters).
    """

    def __init__(
        self,
        reference: np.ndarray,
        triangles: np.ndarray,
        core: tuple[np.ndarray, np.ndarray],
        indenter: str,
        width: int = 320,
        height: int = 240,
    ) -> None:
        self.reference = np.asarray(reference, dtype=float)
        self.triangles = np.asarray(triangles)
        self.width, self.height = int(width), int(height)
        self.model = build_model(self.reference, self.triangles, core, indenter, self.width, self.height)
        self._skin = self.model.mesh("skin").id
        adr, count = self.model.mesh_vertadr[self._skin], self.model.mesh_vertnum[self._skin]
        if count != len(self.reference):
            raise RuntimeError(f"MuJoCo kept {count} of the skin's {len(self.reference)} vertices; cannot deform it")
        self._vertices = slice(adr, adr + count)
        face_adr, face_count = self.model.mesh_faceadr[self._skin], self.model.mesh_facenum[self._skin]
        self._corner_normals = self.model.mesh_facenormal[face_adr : face_adr + face_count].ravel()
        self._corner_vertices = self.model.mesh_face[face_adr : face_adr + face_count].ravel()
        self._normal_adr = self.model.mesh_normaladr[self._skin]
        # compiled mesh coordinates = R^T (x - pos), R and pos the mesh frame MuJoCo chose
        self._mesh_pos = self.model.mesh_pos[self._skin].copy()
        self._mesh_rot = np.empty(9)
        mujoco.mju_quat2Mat(self._mesh_rot, self.model.mesh_quat[self._skin])
        self._mesh_rot = self._mesh_rot.reshape(3, 3)
        self.data = mujoco.MjData(self.model)
        self._context = open_gl_context(self.width, self.height)
        self._gpu = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._gpu)
        self.scene = mujoco.MjvScene(self.model, maxgeom=100)
        self.option = mujoco.MjvOption()
        self.camera = mujoco.MjvCamera()
        self.camera.distance, self.camera.azimuth = CAMERA_DISTANCE_M, CAMERA_AZIMUTH_DEG
        self.camera.elevation = CAMERA_ELEVATION_DEG
        self._viewport = mujoco.MjrRect(0, 0, self.width, self.height)

    def render(self, displacement: np.ndarray, rotation: np.ndarray, tip: np.ndarray, force: np.ndarray) -> np.ndarray:
        """A frame of the skin displaced by `displacement` (V, 3) m, the indenter at (`rotation` (3, 3)
        body->biotac, `tip` (3,) m) and the force (3,) N of the indenter on the skin."""
        if self._context is None:
            raise RuntimeError("this renderer is closed")
        positions = self.reference + np.asarray(displacement, dtype=float)
        self.model.mesh_vert[self._vertices] = (positions - self._mesh_pos) @ self._mesh_rot
        normals = vertex_normals(positions, self.triangles) @ self._mesh_rot
        self.model.mesh_normal[self._normal_adr + self._corner_normals] = normals[self._corner_vertices]
        self._context.make_current()
        mujoco.mjr_uploadMesh(self.model, self._gpu, self._skin)
        self.data.mocap_pos[0], self.data.mocap_quat[0] = tip, _rotation_quat(rotation)
        mujoco.mj_kinematics(self.model, self.data)
        self.camera.lookat[:] = tip
        mujoco.mjv_updateScene(
            self.model, self.data, self.option, None, self.camera, mujoco.mjtCatBit.mjCAT_ALL, self.scene
        )
        mujoco.mjr_render(self._viewport, self.scene, self._gpu)
        frame = np.empty((self.height, self.width, 3), dtype=np.uint8)
        mujoco.mjr_readPixels(frame, None, self._viewport, self._gpu)
        if self._arrow_only(np.asarray(tip, dtype=float), np.asarray(force, dtype=float)):
            self._overlay_arrow(frame)
        return np.flipud(frame).copy()

    def _overlay_arrow(self, frame: np.ndarray) -> None:
        """Draw the scene (now the arrow alone, same camera and lights) and copy its pixels over `frame`
        (rows bottom-up, as read from GL): the arrow is not hidden by the skin or the indenter."""
        mujoco.mjr_render(self._viewport, self.scene, self._gpu)
        arrow = np.empty_like(frame)
        depth = np.empty(frame.shape[:2], dtype=np.float32)
        mujoco.mjr_readPixels(arrow, depth, self._viewport, self._gpu)
        drawn = depth < 1.0  # the cleared depth buffer is 1 where nothing was drawn
        frame[drawn] = arrow[drawn]

    def _arrow_only(self, tip: np.ndarray, force: np.ndarray) -> bool:
        """Replace the scene's geoms by the force arrow ending at `tip` (m); False (scene unchanged) when
        the force (N) is too small to draw."""
        length = min(float(np.linalg.norm(force)) * FORCE_ARROW_M_PER_N, FORCE_ARROW_MAX_M)
        if length < 1e-5:
            return False
        arrow = force * (length / np.linalg.norm(force))
        geom = self.scene.geoms[0]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_ARROW, np.zeros(3), np.zeros(3), np.zeros(9), FORCE_RGBA)
        # MuJoCo's renderer draws an arrow geom over the first half of its size[2] (shaft to 1/3, head to
        # 1/2), so the connector runs to tip + arrow for the arrow drawn to end at the tip.
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_ARROW, 4e-4, tip - arrow, tip + arrow)
        self.scene.ngeom = 1
        return True

    def close(self) -> None:
        """Free the GL resources."""
        if self._context is not None:
            self._context.make_current()
            self._gpu.free()
            self._context.free()
            self._context = None
