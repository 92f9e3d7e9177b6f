"""The skin as a warp-evaluated energy system: membrane + bending + contact, with the fluid volume.

`ShellSystem` owns the mesh data on warp's CPU device and answers `linearize` for Newton: total energy,
gradient and projected sparse Hessian on the free DOFs, and the enclosed volume with its derivatives.
Positions are metres in the sensor frame (`biotac` for the BioTac); forces newtons.
"""

from dataclasses import dataclass, field
from functools import partial

import numpy as np
import warp as wp

from fe import bending, contact, membrane, viscoelastic, volume
from fe.assembly import BlockAssembler, project_psd
from fe.linsolve import SymmetricSolver
from fe.newton import Linearization
from fe.params import ContactSettings, SkinParameters
from fe.wptypes import mat99d, mat1818d, vec6i

CPU_DEVICE = "cpu"
"""Warp device of every array and launch of `ShellSystem`, named explicitly rather than taken from warp's
default (which is `cuda:0` on a CUDA machine): the system writes inputs through `.numpy()` views, which are
the array's own memory only for CPU arrays. The batched GPU path is `fe.batched`."""


def _cpu_array(data: object, dtype: type) -> wp.array:
    """A warp array of `dtype` on `CPU_DEVICE` holding a copy of `data`."""
    return wp.array(data, dtype=dtype, device=CPU_DEVICE)


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


def _shape_arrays(indenter: IndenterState) -> tuple[wp.array, wp.array]:
    """The indenter's kind and dims as the one-system (batch of 1) arrays of the contact kernels."""
    return _cpu_array([indenter.kind], wp.int32), _cpu_array([indenter.dims], wp.vec4d)


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
        stencils, present = bending.build_stencils(mesh.triangles)
        rest_angle, bend_area, coupling = bending.stencil_rest_state(mesh.vertices, stencils, present)
        self._dm_inv_host, self._present, self.rest_angle = dm_inv, present, rest_angle
        self.vertex_area = lumped_areas(mesh.vertices, mesh.triangles)
        self._tri = _cpu_array(mesh.triangles.astype(np.int32), wp.vec3i)
        self._active = _cpu_array([1], wp.int32)  # the kernels' batch of one system, always evaluated
        self._dm_inv = _cpu_array(dm_inv, wp.mat22d)
        self._rest_area = _cpu_array(rest_area, wp.float64)
        self._stencils = _cpu_array(stencils, vec6i)
        self._has_edge = _cpu_array(present, wp.vec3i)
        self._bend_area = _cpu_array(bend_area, wp.float64)
        self._coupling = _cpu_array(coupling, wp.mat33d)
        self._vertex_area = _cpu_array(self.vertex_area, wp.float64)
        vertex_nodes = np.arange(self.n_vertices)[:, None]
        self.bending_stencils = stencils if self.params.bending else stencils[:0]
        """(T,6) nodes of each triangle's bending stencil: its vertices, then the far vertex across each edge."""
        self.assembler = BlockAssembler([mesh.triangles, self.bending_stencils, vertex_nodes], dof_map)
        self._core_mesh = None
        if self.core is not None:
            self._core_vertices = _cpu_array(self.core.vertices, wp.vec3d)
            self._core_triangles = _cpu_array(self.core.triangles.astype(np.int32), wp.vec3i)
            self._core_mesh = wp.Mesh(
                points=_cpu_array(self.core.vertices.astype(np.float32), wp.vec3),
                indices=_cpu_array(self.core.triangles.astype(np.int32).ravel(), wp.int32),
            )
        self.indenter: IndenterState | None = None
        self.x_start = self.x.copy()
        self.lagged_force = np.zeros(self.n_vertices)
        self.lagged_normal = np.zeros((self.n_vertices, 3))
        self._allocate()
        self.linear_solver = SymmetricSolver()

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
    def _allocate(self) -> None:
        """Warp buffers reused by every evaluation (batch axis of 1)."""
        nv, nt, nh = self.n_vertices, len(self.mesh.triangles), len(self.bending_stencils)
        zeros = partial(wp.zeros, device=CPU_DEVICE)
        self._buf = {
            "x": zeros((1, nv), dtype=wp.vec3d),
            "x_start": zeros((1, nv), dtype=wp.vec3d),
            "lagged_force": zeros((1, nv), dtype=wp.float64),
            "lagged_normal": zeros((1, nv), dtype=wp.vec3d),
            "elastic_gradient": zeros((1, nv), dtype=wp.vec3d),
            "membrane_energy": zeros((1, nt), dtype=wp.float64),
            "membrane_hessian": zeros((1, nt), dtype=mat99d),
            "bending_energy": zeros((1, nh), dtype=wp.float64),
            "bending_hessian": zeros((1, nh), dtype=mat1818d),
            "volume": zeros((1, nt), dtype=wp.float64),
            "volume_gradient": zeros((1, nv), dtype=wp.vec3d),
            "volume_hessian": zeros((1, nt), dtype=mat99d),
            "core_energy": zeros((1, nv), dtype=wp.float64),
            "core_gradient": zeros((1, nv), dtype=wp.vec3d),
            "core_hessian": zeros((1, nv), dtype=wp.mat33d),
            "core_gap": zeros((1, nv), dtype=wp.float64),
            "indenter_energy": zeros((1, nv), dtype=wp.float64),
            "indenter_gradient": zeros((1, nv), dtype=wp.vec3d),
            "indenter_hessian": zeros((1, nv), dtype=wp.mat33d),
            "indenter_gap": zeros((1, nv), dtype=wp.float64),
            "indenter_normal": zeros((1, nv), dtype=wp.vec3d),
        }
        self._gent = _cpu_array([self.params.gent_inverse_jm], wp.float64)
        self._friction = _cpu_array([self.params.friction], wp.float64)
        self.set_relaxation(self.params.long_term_fraction)

    def set_relaxation(
        self, scale: float, membrane_stress: np.ndarray | None = None, angle_shift: np.ndarray | None = None
    ) -> None:
        """Viscoelastic terms of the coming solve (`fe.viscoelastic`): membrane and bending moduli scaled by
        `scale` (1: elastic, 1 - g: fully relaxed), a frozen membrane stress (T,2,2) N/m added as
        (1/2) a : (C - I) per reference area, and bending rest angles shifted by `angle_shift` (T,3) rad.
        A new system is fully relaxed (scale 1 - relaxation_fraction, nothing frozen)."""
        self._mu_t = _cpu_array([scale * self.params.membrane_modulus], wp.float64)
        self._kb = _cpu_array([scale * self.params.bending_stiffness], wp.float64)
        self._frozen_stress = None if membrane_stress is None else _cpu_array(membrane_stress, wp.mat22d)
        shifted = self.rest_angle if angle_shift is None or not len(angle_shift) else self.rest_angle + angle_shift
        self._rest_angle = _cpu_array(shifted, wp.vec3d)

    def membrane_stress(self, x: np.ndarray) -> np.ndarray:
        """Elastic (instantaneous) membrane stress resultants (T,2,2) N/m at positions x (V,3) m."""
        p, tri = self.params, self.mesh.triangles
        return membrane.membrane_stress(x, tri, self._dm_inv_host, p.membrane_modulus, p.gent_inverse_jm)

    def bending_angle_change(self, x: np.ndarray) -> np.ndarray:
        """Dihedral-angle changes from the rest state (n_bending, 3) rad at positions x (V,3) m."""
        angles = bending.stencil_rest_state(x, self.bending_stencils, self._present[: len(self.bending_stencils)])[0]
        return angles - self.rest_angle[: len(self.bending_stencils)]

    def _host(self, name: str) -> np.ndarray:
        """A copy of buffer `name` for batch 0."""
        return self._buf[name].numpy()[0].copy()

    def evaluate(self, x: np.ndarray, want_hessian: bool) -> dict[str, np.ndarray | float]:
        """All terms at full positions x (m): energies (J; `bending_energies` per bending stencil), node
        gradients (V,3) (N), Hessian blocks.

        Contact terms use the current `indenter` pose, `x_start`, `lagged_force` and `lagged_normal`.
        """
        nv, nt, nh = self.n_vertices, len(self.mesh.triangles), len(self.bending_stencils)
        buf = self._buf
        buf["x"].numpy()[0] = x
        for name in ("elastic_gradient", "volume_gradient", "core_gradient", "indenter_gradient"):
            buf[name].zero_()
        flag = 1 if want_hessian else 0
        xw = buf["x"]
        wp.launch(
            membrane.membrane_kernel,
            (1, nt),
            [xw, self._tri, self._dm_inv, self._rest_area, self._mu_t, self._gent, flag]
            + [buf["membrane_energy"], buf["elastic_gradient"], buf["membrane_hessian"], self._active],
            device=CPU_DEVICE,
        )
        if self._frozen_stress is not None:
            wp.launch(
                viscoelastic.frozen_stress_kernel,
                (1, nt),
                [xw, self._tri, self._dm_inv, self._rest_area, self._frozen_stress, flag]
                + [buf["membrane_energy"], buf["elastic_gradient"], buf["membrane_hessian"]],
                device=CPU_DEVICE,
            )
        if nh:
            wp.launch(
                bending.bending_kernel,
                (1, nh),
                [xw, self._stencils, self._has_edge, self._rest_angle, self._bend_area, self._coupling, self._kb, flag]
                + [buf["bending_energy"], buf["elastic_gradient"], buf["bending_hessian"], self._active],
                device=CPU_DEVICE,
            )
        wp.launch(
            volume.volume_kernel,
            (1, nt),
            [xw, self._tri, wp.vec3d(*self.volume_origin), flag]
            + [buf["volume"], buf["volume_gradient"], buf["volume_hessian"], self._active],
            device=CPU_DEVICE,
        )
        self._launch_contact(want_hessian)
        out: dict[str, np.ndarray | float] = {
            "elastic_energy": float(buf["membrane_energy"].numpy().sum() + buf["bending_energy"].numpy().sum()),
            "volume": float(buf["volume"].numpy().sum()),
            "core_energy": float(buf["core_energy"].numpy().sum()),
            "indenter_energy": float(buf["indenter_energy"].numpy().sum()),
        }
        for name in ("elastic_gradient", "volume_gradient", "core_gradient", "core_gap", "indenter_gradient"):
            out[name] = self._host(name)
        for name in ("indenter_gap", "indenter_normal"):
            out[name] = self._host(name) if self.indenter is not None else None
        if out["indenter_gap"] is None:
            out["indenter_gap"], out["indenter_normal"] = np.ones(nv), np.zeros((nv, 3))
        if self._core_mesh is None:
            out["core_gap"] = np.ones(nv)
        out["bending_energies"] = self._host("bending_energy")
        for name in ("membrane_hessian", "bending_hessian", "volume_hessian"):
            out[name] = self._host(name) if want_hessian else None
        out["contact_hessian"] = (self._host("core_hessian") + self._host("indenter_hessian")) if want_hessian else None
        return out

    def _launch_contact(self, want_hessian: bool) -> None:
        """Core and indenter contact kernels into the shared buffers."""
        nv, buf = self.n_vertices, self._buf
        kappa = wp.float64(self.contact_settings.penalty_stiffness)
        for name in ("core_energy", "core_hessian", "indenter_energy", "indenter_hessian"):
            buf[name].zero_()
        if self._core_mesh is not None:
            wp.launch(
                contact.core_contact_kernel,
                (1, nv),
                [buf["x"], self._core_mesh.id, self._core_vertices, self._core_triangles, self._vertex_area]
                + [wp.float64(self.core.offset), kappa, buf["core_energy"], buf["core_gradient"]]
                + [buf["core_hessian"], buf["core_gap"], self._active],
                device=CPU_DEVICE,
            )
        ind = self.indenter
        if ind is None:
            return
        buf["x_start"].numpy()[0] = self.x_start
        buf["lagged_force"].numpy()[0] = self.lagged_force
        buf["lagged_normal"].numpy()[0] = self.lagged_normal
        rotation_start = ind.rotation if ind.rotation_start is None else ind.rotation_start
        wp.launch(
            contact.indenter_contact_kernel,
            (1, nv),
            [buf["x"], buf["x_start"], self._vertex_area, *_shape_arrays(ind)]
            + [_cpu_array([ind.rotation], wp.mat33d), _cpu_array([ind.translation], wp.vec3d)]
            + [_cpu_array([rotation_start], wp.mat33d), _cpu_array([ind.translation_start], wp.vec3d)]
            + [_cpu_array([ind.offset], wp.float64), kappa, self._friction, buf["lagged_force"]]
            + [buf["lagged_normal"], wp.float64(self.contact_settings.slip_length), 1 if want_hessian else 0]
            + [buf["indenter_energy"], buf["indenter_gradient"], buf["indenter_hessian"], buf["indenter_gap"]]
            + [buf["indenter_normal"], self._active],
            device=CPU_DEVICE,
        )

    def indenter_proximity(self, x: np.ndarray, indenter: IndenterState) -> tuple[np.ndarray, np.ndarray]:
        """Gap (m, negative inside the contact band) and unit SDF normal (V,3) of every vertex at x to `indenter`."""
        buf = self._buf
        buf["x"].numpy()[0] = x
        wp.launch(
            contact.indenter_gap_kernel,
            (1, self.n_vertices),
            [buf["x"], *_shape_arrays(indenter), _cpu_array([indenter.rotation], wp.mat33d)]
            + [_cpu_array([indenter.translation], wp.vec3d), _cpu_array([indenter.offset], wp.float64)]
            + [buf["indenter_gap"], buf["indenter_normal"]],
            device=CPU_DEVICE,
        )
        return self._host("indenter_gap"), self._host("indenter_normal")

    def linearize(self, q: np.ndarray, pressure: float, want_matrix: bool, projected: bool = False) -> Linearization:
        """Newton's view of the system at free positions q (m) and fluid pressure (Pa).

        The matrix is the Hessian of the energy minus pressure times the volume Hessian; with `projected`
        each membrane, bending and contact block is first projected to PSD.
        """
        terms = self.evaluate(self.positions(q), want_matrix)
        energy = terms["elastic_energy"] + terms["core_energy"] + terms["indenter_energy"]
        gradient = terms["elastic_gradient"] + terms["core_gradient"] + terms["indenter_gradient"]
        matrix = None
        if want_matrix:
            energy_blocks = [terms["membrane_hessian"], terms["bending_hessian"], terms["contact_hessian"]]
            if projected:
                energy_blocks = [project_psd(block) for block in energy_blocks]
            energy_blocks[0] = energy_blocks[0] - pressure * terms["volume_hessian"]
            matrix = self.assembler.assemble(energy_blocks)
        free = self.free_dofs
        return Linearization(
            energy=energy,
            gradient=gradient.reshape(-1)[free],
            volume=terms["volume"],
            volume_gradient=terms["volume_gradient"].reshape(-1)[free],
            matrix=matrix,
        )
