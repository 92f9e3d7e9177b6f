"""The skin as a warp-evaluated energy system: membrane + bending + contact, with the fluid volume.

`ShellSystem` owns the mesh data on the warp device and answers `linearize` for Newton: total energy,
gradient and projected sparse Hessian on the free DOFs, and the enclosed volume with its derivatives.
Positions are metres in the sensor frame (`biotac` for the BioTac); forces newtons.
"""

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from fe import bending, contact, membrane, volume
from fe.assembly import BlockAssembler, project_psd
from fe.newton import Linearization
from fe.params import ContactSettings, SkinParameters
from fe.wptypes import mat99d, mat1212d


@dataclass(frozen=True)
class ShellMesh:
    """A triangle mid-surface (m) whose right-hand normals point out of the fluid cavity.

    `fixed` marks vertices held in place (anchors, pinned rims), shape (V,), or single held
    coordinates, shape (V,3); every boundary vertex must be fixed for the enclosed volume to be meaningful.
    """

    vertices: np.ndarray
    triangles: np.ndarray
    fixed: np.ndarray

    def __post_init__(self) -> None:
        v, t, f = self.vertices, self.triangles, self.fixed
        if v.ndim != 2 or v.shape[1] != 3 or t.ndim != 2 or t.shape[1] != 3 or f.shape not in ((len(v),), (len(v), 3)):
            raise ValueError("ShellMesh needs vertices (V,3), triangles (T,3) and fixed (V,) or (V,3)")
        if t.size and (t.min() < 0 or t.max() >= len(v)):
            raise ValueError("triangle indices out of range")


@dataclass(frozen=True)
class RigidSurface:
    """A closed rigid triangle surface (m), outward normals; the skin stays `offset` m outside it."""

    vertices: np.ndarray
    triangles: np.ndarray
    offset: float


@dataclass
class IndenterState:
    """Rigid indenter pose for the current increment and at its start (friction slip is measured from it).

    Rotations (3,3) map the indenter body frame (tip at the origin, body along +z) to the sensor frame;
    translations are tip positions (m); `offset` (m) is the skin's half-thickness outside the mid-surface.
    `rotation_start` None means the rotation did not change over the increment.
    """

    kind: int
    dims: tuple[float, float, float, float]
    rotation: np.ndarray
    translation: np.ndarray
    translation_start: np.ndarray
    offset: float
    rotation_start: np.ndarray | None = None


def lumped_areas(vertices: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """One third of the adjacent triangle areas per vertex (m^2)."""
    p0, p1, p2 = (vertices[triangles[:, k]] for k in range(3))
    area = 0.5 * np.linalg.norm(np.cross(p1 - p0, p2 - p0), axis=1)
    return np.bincount(triangles.ravel(), weights=np.repeat(area / 3.0, 3), minlength=len(vertices))


@dataclass
class ShellSystem:
    """Energy system of one skin (batch of 1 for the Newton solve; kernels take a batch axis)."""

    mesh: ShellMesh
    params: SkinParameters
    contact_settings: ContactSettings = field(default_factory=ContactSettings)
    core: RigidSurface | None = None
    volume_origin: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        mesh = self.mesh
        self.n_vertices = len(mesh.vertices)
        fixed = np.broadcast_to(mesh.fixed.reshape(self.n_vertices, -1), (self.n_vertices, 3))
        self.fixed_dofs = fixed.copy()
        free_dofs = np.flatnonzero(~fixed.reshape(-1))
        dof_map = -np.ones(3 * self.n_vertices, dtype=np.int64)
        dof_map[free_dofs] = np.arange(len(free_dofs))
        self.free_dofs = free_dofs
        self.x = mesh.vertices.astype(np.float64).copy()
        dm_inv, rest_area = membrane.reference_frames(mesh.vertices, mesh.triangles)
        self.hinges = bending.build_hinges(mesh.triangles)
        rest_angle, rest_weight = bending.hinge_rest_state(mesh.vertices, mesh.triangles, self.hinges)
        self.vertex_area = lumped_areas(mesh.vertices, mesh.triangles)
        self._tri = wp.array(mesh.triangles.astype(np.int32), dtype=wp.vec3i)
        self._dm_inv = wp.array(dm_inv, dtype=wp.mat22d)
        self._rest_area = wp.array(rest_area, dtype=wp.float64)
        self._hinges = wp.array(self.hinges, dtype=wp.vec4i)
        self._rest_angle = wp.array(rest_angle, dtype=wp.float64)
        self._rest_weight = wp.array(rest_weight, dtype=wp.float64)
        self._vertex_area = wp.array(self.vertex_area, dtype=wp.float64)
        vertex_nodes = np.arange(self.n_vertices)[:, None]
        if not self.params.bending:
            self.hinges = self.hinges[:0]
        self.assembler = BlockAssembler([mesh.triangles, self.hinges, vertex_nodes], dof_map)
        self._core_mesh = None
        if self.core is not None:
            self._core_vertices = wp.array(self.core.vertices, dtype=wp.vec3d)
            self._core_triangles = wp.array(self.core.triangles.astype(np.int32), dtype=wp.vec3i)
            self._core_mesh = wp.Mesh(
                points=wp.array(self.core.vertices.astype(np.float32), dtype=wp.vec3),
                indices=wp.array(self.core.triangles.astype(np.int32).ravel(), dtype=wp.int32),
            )
        self.indenter: IndenterState | None = None
        self.x_start = self.x.copy()
        self.lagged_force = np.zeros(self.n_vertices)
        self.lagged_normal = np.zeros((self.n_vertices, 3))

    # -- state -------------------------------------------------------------------------------
    def positions(self, q: np.ndarray) -> np.ndarray:
        """Full (V,3) positions (m) with the free DOFs set to q."""
        x = self.x.copy()
        x.reshape(-1)[self.free_dofs] = q
        return x

    def free_coordinates(self, x: np.ndarray) -> np.ndarray:
        """The free DOFs (m) of full positions x."""
        return x.reshape(-1)[self.free_dofs].copy()

    # -- evaluation --------------------------------------------------------------------------
    def evaluate(self, x: np.ndarray, want_hessian: bool) -> dict[str, np.ndarray | float]:
        """All terms at full positions x (m): energies (J), node gradients (V,3) (N), Hessian blocks."""
        nv, nt, nh = self.n_vertices, len(self.mesh.triangles), len(self.hinges)
        xw = wp.array(x[None], dtype=wp.vec3d)
        flag = 1 if want_hessian else 0
        out: dict[str, np.ndarray | float] = {}

        grad = wp.zeros((1, nv), dtype=wp.vec3d)
        e = wp.zeros((1, nt), dtype=wp.float64)
        h9 = wp.zeros((1, nt if want_hessian else 0), dtype=mat99d)
        mu_t = wp.array([self.params.membrane_modulus], dtype=wp.float64)
        wp.launch(
            membrane.membrane_kernel, (1, nt), [xw, self._tri, self._dm_inv, self._rest_area, mu_t, flag, e, grad, h9]
        )
        out["elastic_energy"] = float(e.numpy().sum())
        out["membrane_hessian"] = h9.numpy()[0] if want_hessian else None

        out["bending_hessian"] = np.zeros((0, 12, 12))
        if nh:
            eb = wp.zeros((1, nh), dtype=wp.float64)
            h12 = wp.zeros((1, nh if want_hessian else 0), dtype=mat1212d)
            kb = wp.array([self.params.bending_stiffness], dtype=wp.float64)
            wp.launch(
                bending.bending_kernel,
                (1, nh),
                [xw, self._hinges, self._rest_angle, self._rest_weight, kb, flag, eb, grad, h12],
            )
            out["elastic_energy"] += float(eb.numpy().sum())
            out["bending_hessian"] = h12.numpy()[0] if want_hessian else None
        out["elastic_gradient"] = grad.numpy()[0]

        vgrad = wp.zeros((1, nv), dtype=wp.vec3d)
        ev = wp.zeros((1, nt), dtype=wp.float64)
        hv = wp.zeros((1, nt if want_hessian else 0), dtype=mat99d)
        wp.launch(volume.volume_kernel, (1, nt), [xw, self._tri, wp.vec3d(*self.volume_origin), flag, ev, vgrad, hv])
        out["volume"] = float(ev.numpy().sum())
        out["volume_gradient"] = vgrad.numpy()[0]
        out["volume_hessian"] = hv.numpy()[0] if want_hessian else None

        out.update(self._contact_terms(xw, want_hessian))
        return out

    def _contact_terms(self, xw: wp.array, want_hessian: bool) -> dict[str, np.ndarray | float]:
        nv = self.n_vertices
        kappa = wp.float64(self.contact_settings.penalty_stiffness)
        terms: dict[str, np.ndarray | float] = {}
        core_grad = wp.zeros((1, nv), dtype=wp.vec3d)
        core_h = wp.zeros((1, nv), dtype=wp.mat33d)
        core_gap = wp.zeros((1, nv), dtype=wp.float64)
        core_e = wp.zeros((1, nv), dtype=wp.float64)
        if self._core_mesh is not None:
            wp.launch(
                contact.core_contact_kernel,
                (1, nv),
                [
                    xw,
                    self._core_mesh.id,
                    self._core_vertices,
                    self._core_triangles,
                    self._vertex_area,
                    wp.float64(self.core.offset),
                    kappa,
                    core_e,
                    core_grad,
                    core_h,
                    core_gap,
                ],
            )
        terms["core_energy"] = float(core_e.numpy().sum())
        terms["core_gradient"] = core_grad.numpy()[0]
        terms["core_gap"] = core_gap.numpy()[0] if self._core_mesh is not None else np.ones(nv)
        ind_grad = wp.zeros((1, nv), dtype=wp.vec3d)
        ind_h = wp.zeros((1, nv), dtype=wp.mat33d)
        ind_gap = wp.zeros((1, nv), dtype=wp.float64)
        ind_n = wp.zeros((1, nv), dtype=wp.vec3d)
        ind_e = wp.zeros((1, nv), dtype=wp.float64)
        ind = self.indenter
        if ind is not None:
            wp.launch(
                contact.indenter_contact_kernel,
                (1, nv),
                [
                    xw,
                    wp.array(self.x_start[None], dtype=wp.vec3d),
                    self._vertex_area,
                    ind.kind,
                    wp.vec4d(*ind.dims),
                    wp.array([ind.rotation], dtype=wp.mat33d),
                    wp.array([ind.translation], dtype=wp.vec3d),
                    wp.array([ind.rotation if ind.rotation_start is None else ind.rotation_start], dtype=wp.mat33d),
                    wp.array([ind.translation_start], dtype=wp.vec3d),
                    wp.array([ind.offset], dtype=wp.float64),
                    kappa,
                    wp.array([self.params.friction], dtype=wp.float64),
                    wp.array(self.lagged_force[None], dtype=wp.float64),
                    wp.array(self.lagged_normal[None], dtype=wp.vec3d),
                    wp.float64(self.contact_settings.slip_length),
                    1 if want_hessian else 0,
                    ind_e,
                    ind_grad,
                    ind_h,
                    ind_gap,
                    ind_n,
                ],
            )
        terms["indenter_energy"] = float(ind_e.numpy().sum())
        terms["indenter_gradient"] = ind_grad.numpy()[0]
        terms["indenter_gap"] = ind_gap.numpy()[0] if ind is not None else np.ones(nv)
        terms["indenter_normal"] = ind_n.numpy()[0]
        terms["contact_hessian"] = (core_h.numpy()[0] + ind_h.numpy()[0]) if want_hessian else None
        return terms

    def indenter_gaps(self, x: np.ndarray, indenter: IndenterState) -> np.ndarray:
        """Gap (m) of every skin vertex at positions x (V,3) to `indenter`: negative inside the contact band."""
        gap = wp.zeros((1, self.n_vertices), dtype=wp.float64)
        wp.launch(
            contact.indenter_gap_kernel,
            (1, self.n_vertices),
            [
                wp.array(x[None], dtype=wp.vec3d),
                indenter.kind,
                wp.vec4d(*indenter.dims),
                wp.array([indenter.rotation], dtype=wp.mat33d),
                wp.array([indenter.translation], dtype=wp.vec3d),
                wp.array([indenter.offset], dtype=wp.float64),
                gap,
            ],
        )
        return gap.numpy()[0]

    def linearize(self, q: np.ndarray, pressure: float, want_matrix: bool) -> Linearization:
        """Newton's view of the system at free positions q (m) and fluid pressure (Pa)."""
        terms = self.evaluate(self.positions(q), want_matrix)
        energy = terms["elastic_energy"] + terms["core_energy"] + terms["indenter_energy"]
        gradient = terms["elastic_gradient"] + terms["core_gradient"] + terms["indenter_gradient"]
        matrix = None
        if want_matrix:
            tri_blocks = project_psd(terms["membrane_hessian"]) - pressure * terms["volume_hessian"]
            blocks = [
                tri_blocks,
                project_psd(terms["bending_hessian"]),
                project_psd(terms["contact_hessian"]),
            ]
            matrix = self.assembler.assemble(blocks)
        free = self.free_dofs
        return Linearization(
            energy=energy,
            gradient=gradient.reshape(-1)[free],
            volume=terms["volume"],
            volume_gradient=terms["volume_gradient"].reshape(-1)[free],
            matrix=matrix,
        )
