"""The FE engine: B skins solved together on any warp device (CPU or CUDA): energies, Newton, linear algebra.

`InflatedSkin` is the model (mesh, core, parameters, settings) with its starting state; `BatchedShell` stacks
B independent systems of it (each with its own indenter, pose, friction lagging, viscoelastic state and
trapped air) into warp arrays with a leading batch axis and evaluates every energy term for all of them with
one launch per kernel (the kernels of fe/membrane.py, with the viscoelastic frozen stress, fe/bending.py,
fe/volume.py and fe/contact.py), then assembles the B Newton matrices into one batched block-sparse matrix on
the device. The linear algebra follows the device: one sparse direct factorisation per system on the CPU
(`fe.linsolve.BatchedDirectSolver`: PARDISO or SuperLU, with chord steps that reuse it near convergence),
batched CG on a GPU (`fe.device_solver.BatchedCG`). Newton solves the KKT system of the held volume through
its Schur complement (K u1 = -r, K u2 = b; trapped air adds its compliance), backtracks on an
augmented-Lagrangian merit function (else on the residual norm), and refreshes the lagged friction forces
near convergence. A step of non-positive curvature, or one with no acceptable length, is retried with
diagonal damping (K + s diag(K), s = 1e-2 ... 1e2).

Newton runs in rounds (`round`: `evaluate_round`, `settle`, `check`, `iterate`) in which every system does
one evaluation, wherever it is: at its positions (then a convergence check and a new direction) or at the
next trial point of its line search or chord step. So a system that backtracks costs the others nothing
and systems can join and leave between rounds (`fe.batched_stepper.BatchedStepper.admit`).
Units: m, N, Pa, m^3; positions in the sensor (biotac) frame.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np
import warp as wp

from fe import batched_kernels as bk
from fe import bending, contact, membrane, volume
from fe.device_solver import CG_NEGATIVE_CURVATURE, BatchedBlockMatrix, BatchedCG, BlockPattern
from fe.linsolve import BatchedDirectSolver
from fe.params import ContactSettings, NewtonSettings, SkinParameters
from fe.shell import lumped_areas
from fe.surface_quadrature import rule
from fe.trapped_air import TrappedAir
from fe.wptypes import launch, mat99d, mat1818d, vec6i

_ENERGY_RESOLUTION = 1e-12
LINEAR_SOLVERS = ("auto", "direct", "cg")
"""Newton's linear algebra: "auto" follows the device (direct on the CPU, CG on a GPU); "direct" and "cg"
force one (CG on the CPU runs the GPU's algebra where there is no GPU, e.g. in tests)."""
FORCING = ("adaptive", "strict")
"""How tightly each Newton step's linear systems are solved (`BatchedShell._forcing`)."""
_ETA_MAX = 0.1
"""Loosest relative CG tolerance of an "adaptive" Newton step."""
_DAMPING = np.array([0.0, 1e-2, 1e-1, 1.0, 1e1, 1e2])
"""Relative diagonal damping of each attempt: the exact Newton matrix first, then more damping each time a
system finds no step."""


@dataclass(frozen=True)
class InflatedSkin:
    """Everything a batched solve needs from an inflated BioTac model (SI units, biotac frame).

    vertices (V,3), triangles (T,3), fixed (V,) or (V,3): the rest mid-surface mesh; core_*: the rigid core
    (no triangles: none) and the skin's clearance from it (m); volume_origin (3,) m; reference (V,3) m,
    pressure (Pa) and target_volume (m^3): the state every trajectory starts from (inflated, or the rest
    mesh itself for a model about to be inflated).
    """

    vertices: np.ndarray
    triangles: np.ndarray
    fixed: np.ndarray
    core_vertices: np.ndarray
    core_triangles: np.ndarray
    core_offset: float
    volume_origin: np.ndarray
    params: SkinParameters
    contact: ContactSettings
    newton: NewtonSettings
    reference: np.ndarray
    pressure: float
    target_volume: float
    air_boyle: float = 0.0
    """Boyle constant (J) of the trapped air at the inflated state (`fe.trapped_air`; 0: none)."""
    indenter_offset: float | None = None
    """Distance (m) the indenter keeps from the mid-surface (None: half the skin thickness)."""

    @property
    def indenter_half_layer(self) -> float:
        """The half-layer h (m) between the mid-surface and the indenter: `indenter_offset`, else half the skin
        thickness (the one rule of the contact kernels, the stepper's checks and `fe.sensor`'s first touch)."""
        return 0.5 * self.params.thickness if self.indenter_offset is None else self.indenter_offset

    @classmethod
    def at_rest(
        cls,
        vertices: np.ndarray,
        triangles: np.ndarray,
        fixed: np.ndarray,
        params: SkinParameters,
        contact: ContactSettings = ContactSettings(),
        newton: NewtonSettings = NewtonSettings(),
        core: tuple[np.ndarray, np.ndarray, float] | None = None,
        volume_origin: np.ndarray | None = None,
        indenter_offset: float | None = None,
    ) -> InflatedSkin:
        """A skin whose starting state is its unloaded rest mesh (pressure 0, volume whatever it encloses):
        the model to inflate (`fe.batched_stepper.BatchedStepper.hold_volume`). `core`: vertices, triangles
        and clearance (m) of a rigid core, None for none."""
        core_v, core_t, core_offset = core if core is not None else (np.zeros((0, 3)), np.zeros((0, 3), int), 0.0)
        return cls(
            vertices=np.asarray(vertices, dtype=np.float64),
            triangles=np.asarray(triangles),
            fixed=np.asarray(fixed),
            core_vertices=np.asarray(core_v, dtype=np.float64),
            core_triangles=np.asarray(core_t),
            core_offset=float(core_offset),
            volume_origin=np.zeros(3) if volume_origin is None else np.asarray(volume_origin, dtype=np.float64),
            params=params,
            contact=contact,
            newton=newton,
            reference=np.asarray(vertices, dtype=np.float64),
            pressure=0.0,
            target_volume=float("nan"),
            indenter_offset=indenter_offset,
        )

    def save(self, path: Path) -> None:
        """Write to an .npz file (arrays, plus the settings as JSON)."""
        arrays = {f.name: np.asarray(getattr(self, f.name)) for f in fields(self) if f.name not in _SETTINGS}
        arrays["indenter_offset"] = np.zeros(0) if self.indenter_offset is None else np.asarray(self.indenter_offset)
        settings = {name: asdict(getattr(self, name)) for name in _SETTINGS}
        np.savez(path, settings=json.dumps(settings), **arrays)

    @classmethod
    def load(cls, path: Path) -> InflatedSkin:
        """Read a file written by `save`."""
        with np.load(path) as data:
            settings = json.loads(str(data["settings"]))
            values = {name: data[name] for name in data.files if name != "settings"}
        for name in ("core_offset", "pressure", "target_volume", "air_boyle", "indenter_offset"):
            if name in values:
                values[name] = None if values[name].shape == (0,) else float(values[name])
        built = {name: _SETTINGS[name](**settings[name]) for name in _SETTINGS}
        return cls(**values, **built)


_SETTINGS = {"params": SkinParameters, "contact": ContactSettings, "newton": NewtonSettings}
_SHARED = ("vertices", "triangles", "fixed", "core_vertices", "core_triangles", "core_offset", "volume_origin")
"""InflatedSkin fields every system of one batch shares (with `contact` and `newton`); the others (parameters,
starting state, trapped air, indenter offset) may differ per system."""


def per_system(skin: InflatedSkin | Sequence[InflatedSkin], batch: int) -> list[InflatedSkin]:
    """One skin per system of a batch of `batch`: `skin` for all, or a sequence of `batch` skins of one mesh,
    core, contact and Newton settings (each with its own parameters and starting state)."""
    skins = [skin] * batch if isinstance(skin, InflatedSkin) else list(skin)
    if len(skins) != batch:
        raise ValueError(f"{len(skins)} skins for {batch} systems")
    first = skins[0]
    for other in skins[1:]:
        if other is first:
            continue
        same = all(np.array_equal(getattr(first, name), getattr(other, name)) for name in _SHARED)
        if not (same and other.contact == first.contact and other.newton == first.newton):
            raise ValueError("the skins of one batch must share mesh, core, contact and Newton settings")
    return skins


def _skin_values(skin: InflatedSkin) -> dict[str, float]:
    """The per-system scalars of a skin that the kernels read: long-term moduli (Pa m, N m), Gent 1/Jm,
    friction coefficient and the indenter's half-layer (m)."""
    p = skin.params
    return {
        "mu_t": p.long_term_fraction * p.membrane_modulus,
        "gent_beta": p.gent_inverse_jm,
        "bending_stiffness": p.long_term_fraction * p.bending_stiffness,
        "friction": p.friction,
        "offset": skin.indenter_half_layer,
        "layer_mu": p.long_term_fraction * p.mu_nh,
    }


@dataclass
class BatchLinearization:
    """Per-system scalars of one evaluation, (B,) host arrays: energy (J), enclosed volume (m^3), infinity
    and 2-norm of the free-DOF residual (N), and the largest nodal load max(|grad E|, |p grad V|) (N);
    the vectors stay on the device (`BatchedShell.residual`, `.gradient`, `.bvec`)."""

    energy: np.ndarray
    volume: np.ndarray
    residual_inf: np.ndarray
    residual_2: np.ndarray
    load: np.ndarray


AT_X, ENERGY_SEARCH, RESIDUAL_SEARCH, CHORD = 0, 1, 2, 3
"""Newton phases of a system: evaluated at its positions (ready for a convergence check and a new
direction), backtracking along its direction on the energy merit function or on the residual norm, or
trying a chord step (the last factorisation reused; kept when it cuts the residual enough)."""


_FLAGS = ("running", "converged", "failed", "refreshed", "factorized", "chord_failed", "has_hessian")
_COUNTS = ("iterations", "passes", "phase", "backtracks", "attempt")
"""Boolean and integer fields of `NewtonBatch` (the others but `message` are float64)."""


@dataclass
class NewtonBatch:
    """Per-system Newton state of a `BatchedShell` ((B,) host arrays), kept between rounds so that systems
    start, search and stop independently.

    pressure (Pa), target volume (m^3); whether a system runs, converged, failed (no step found even with
    the strongest damping) or just had its lagged friction refreshed; its Newton iteration and
    friction-refresh counts; why it stopped; its final residual (N) and volume (m^3); the residual (N) and
    CG tolerance of its last Newton step (NaN before the first). Line search: `phase` (AT_X,
    ENERGY_SEARCH, RESIDUAL_SEARCH), the trial `step` along (dq, dp), backtracks so far, the damping
    `attempt` (0: exact Newton matrix), the pressure step dp (Pa), the merit function's pressure new_p
    (Pa), penalty rho, value phi0 (J) and slope (J) at the start, and the residual 2-norm there (N).
    Chord steps: whether the linear solver holds a factorisation from this solve (`factorized`), whether
    the last chord from the current positions failed, and whether the shell's Hessian buffers hold the
    system's Hessians at its positions (`has_hessian`).
    """

    pressure: np.ndarray
    target: np.ndarray
    running: np.ndarray
    converged: np.ndarray
    failed: np.ndarray
    refreshed: np.ndarray
    iterations: np.ndarray
    passes: np.ndarray
    message: list[str]
    residual: np.ndarray
    volume: np.ndarray
    last_residual: np.ndarray
    last_eta: np.ndarray
    phase: np.ndarray
    step: np.ndarray
    backtracks: np.ndarray
    attempt: np.ndarray
    dp: np.ndarray
    new_p: np.ndarray
    rho: np.ndarray
    phi0: np.ndarray
    slope: np.ndarray
    rnorm: np.ndarray
    factorized: np.ndarray
    chord_failed: np.ndarray
    has_hessian: np.ndarray

    @classmethod
    def idle(cls, batch: int, target_volume: np.ndarray | float) -> NewtonBatch:
        """B systems, none running, holding their volumes at `target_volume` (m^3)."""
        dtype = dict.fromkeys(_FLAGS, bool) | dict.fromkeys(_COUNTS, np.int64)
        values = {f.name: np.zeros(batch, dtype=dtype.get(f.name, np.float64)) for f in fields(cls)}
        values["target"] = np.broadcast_to(np.asarray(target_volume, dtype=np.float64), (batch,)).copy()
        values["message"] = ["inactive"] * batch
        values["last_residual"] = np.full(batch, np.nan)
        return cls(**values)


class BatchedShell:
    """`batch` copies of an `InflatedSkin` on a warp `device`; indenter i of the batch is `indenters[i]`,
    given as (kind, dims) of `fe.indenter_sdf` (any mix: the contact kernels read each system's own).
    `forcing`: one of `FORCING`, how tightly the CG solves each Newton step (the converged states do not
    depend on it, only the work); `linear`: one of `LINEAR_SOLVERS`; `later`: skins systems may take later
    (`set_skin`), whose bending and relaxation the batch is built for too."""

    def __init__(
        self,
        skin: InflatedSkin | Sequence[InflatedSkin],
        indenters: list[tuple[int, tuple[float, float, float, float]]],
        device: str = "cpu",
        cg_max_iterations: int = 20000,
        forcing: str = "adaptive",
        linear: str = "auto",
        later: Sequence[InflatedSkin] = (),
    ) -> None:
        if forcing not in FORCING:
            raise ValueError(f"forcing must be one of {FORCING}, got {forcing!r}")
        if linear not in LINEAR_SOLVERS:
            raise ValueError(f"linear must be one of {LINEAR_SOLVERS}, got {linear!r}")
        self.skins = per_system(skin, len(indenters))
        """The model of each system (`per_system`): one mesh, parameters and starting state per system."""
        skin = self.skins[0]
        self.skin, self.device, self.batch = skin, device, len(indenters)
        params = [s.params for s in [*self.skins, *later]]
        self.cg_max_iterations, self.forcing = cg_max_iterations, forcing
        B, V = self.batch, len(skin.vertices)
        self.n_vertices = V
        tri = skin.triangles
        fixed = np.broadcast_to(np.asarray(skin.fixed).reshape(V, -1), (V, 3))
        self.free = (~fixed).astype(np.float64)
        self.fixed = fixed.copy()
        dm_inv, rest_area = membrane.reference_frames(skin.vertices, tri)
        stencils, present = bending.build_stencils(tri)
        rest_angle, bend_area, coupling = bending.stencil_rest_state(skin.vertices, stencils, present)
        stencils = stencils if any(p.bending for p in params) else stencils[:0]
        self.vertex_area = lumped_areas(skin.vertices, tri)
        self._dm_inv, self._rest_angle, self._present = dm_inv, rest_angle[: len(stencils)], present[: len(stencils)]
        self._stencils = stencils
        self.n_triangles, self.n_bending = len(tri), len(stencils)
        self.relaxes = any(p.relaxation_fraction > 0.0 for p in params)
        """Whether the skin relaxes (viscoelastic: the membrane's frozen stresses and the bending rest angles move)."""
        self.air = TrappedAir(np.array([s.air_boyle for s in self.skins], dtype=np.float64))
        """The cavity's trapped air, one bubble per system (`fe.trapped_air`)."""
        arr = lambda a, dtype: wp.array(a, dtype=dtype, device=device)  # noqa: E731
        per_batch = lambda values: arr(np.asarray(values, dtype=np.float64), wp.float64)  # noqa: E731
        z = lambda shape, dtype: wp.zeros(shape, dtype=dtype, device=device)  # noqa: E731
        cs = skin.contact
        self._static = {
            "triangles": arr(tri.astype(np.int32), wp.vec3i),
            "dm_inv": arr(dm_inv, wp.mat22d),
            "rest_area": arr(rest_area, wp.float64),
            "stencils": arr(stencils.astype(np.int32), vec6i),
            "has_edge": arr(present[: len(stencils)], wp.vec3i),
            "rest_angle": arr(np.broadcast_to(rest_angle[: len(stencils)], (B, len(stencils), 3)), wp.vec3d),
            "bend_area": arr(bend_area[: len(stencils)], wp.float64),
            "coupling": arr(coupling[: len(stencils)], wp.mat33d),
            "vertex_area": arr(self.vertex_area, wp.float64),
            "frozen_stress": z((B, len(tri)), wp.mat22d),
            "kappa": wp.float64(cs.penalty_stiffness),
            "min_stretch": wp.float64(cs.min_stretch),
            "quadrature": arr(rule(cs.surface_rule), wp.vec4d),
            "slip_eps": wp.float64(cs.slip_length),
            "origin": wp.vec3d(*skin.volume_origin),
            "core_offset": wp.float64(skin.core_offset),
            "free": arr(self.free, wp.vec3d),
        }
        values = [_skin_values(s) for s in self.skins]
        self._static |= {name: per_batch([v[name] for v in values]) for name in values[0]}
        self._core_mesh = None
        self.has_core = bool(len(skin.core_triangles))
        """Whether the skin has a rigid core (the core gaps in `buf["core_gap"]` mean something)."""
        clamped = np.broadcast_to(fixed.all(axis=1), (B, V))  # rigid on the rigid base: no core contact to find
        if self.has_core:
            self._static["core_vertices"] = arr(skin.core_vertices, wp.vec3d)
            self._static["core_triangles"] = arr(skin.core_triangles.astype(np.int32), wp.vec3i)
            self._core_mesh = wp.Mesh(
                points=arr(skin.core_vertices.astype(np.float32), wp.vec3),
                indices=arr(skin.core_triangles.astype(np.int32).ravel(), wp.int32),
            )
            self._static["core"] = self._core_mesh.id
        nt, nh = len(tri), len(stencils)
        self.x = z((B, V), wp.vec3d)
        self.x_trial = z((B, V), wp.vec3d)
        self.x_start = z((B, V), wp.vec3d)
        self.lagged_force = z((B, V), wp.float64)
        self.lagged_normal = z((B, V), wp.vec3d)
        self.gradients = z((3, B, V), wp.vec3d)  # elastic, core, indenter
        self.buf = {
            "elastic_gradient": self.gradients[0],
            "core_gradient": self.gradients[1],
            "indenter_gradient": self.gradients[2],
            "queried_at": z((B, V), wp.vec3d),
            "queried_gap": arr(np.where(clamped, np.inf, -1.0), wp.float64),  # -1: not searched yet
            "membrane_energy": z((B, nt), wp.float64),
            "membrane_hessian": z((B, nt), mat99d),
            "bending_energy": z((B, nh), wp.float64),
            "bending_hessian": z((B, nh), mat1818d),
            "volume": z((B, nt), wp.float64),
            "volume_gradient": z((B, V), wp.vec3d),
            "volume_hessian": z((B, nt), mat99d),
            "core_energy": z((B, V), wp.float64),
            "core_hessian": z((B, V), wp.mat33d),
            "core_gap": z((B, V), wp.float64),
            "indenter_energy": z((B, V), wp.float64),
            "indenter_hessian": z((B, V), wp.mat33d),
            "indenter_gap": z((B, V), wp.float64),
            "indenter_normal": z((B, V), wp.vec3d),
            "indenter_face_energy": z((B, nt), wp.float64),
            "indenter_face_gap": z((B, nt), wp.float64),
            "indenter_face_moved": z((B, nt), wp.float64),
            "indenter_vertex_force": z((B, V), wp.vec3d),
        }
        """What the energy kernels write (and the core search's memory), each under the name of its kernel
        argument (`_launch`)."""
        self._lag_buf = {
            "indenter_face_energy": z((B, nt), wp.float64),
            "indenter_gradient": z((B, V), wp.vec3d),
            "indenter_face_gap": z((B, nt), wp.float64),
            "indenter_vertex_force": z((B, V), wp.vec3d),
        }
        """Scratch outputs of the surface contact evaluated for the friction lagging (`lag_contact`), so that
        it leaves the last evaluation's buffers as they are."""
        self.residual = z((B, V), wp.vec3d)
        self.gradient = z((B, V), wp.vec3d)
        self.bvec = z((B, V), wp.vec3d)
        self.dq = z((B, V), wp.vec3d)
        self.rhs = z((2 * B, V), wp.vec3d)
        self.kdq = z((B, V), wp.vec3d)
        self._stats = z((B, 3), wp.float64)
        self._totals = z((B, 2), wp.float64)
        self._pair = z((B, 2), wp.float64)
        self._scratch: dict[str, wp.array] = {}
        self._candidate = z((B, V), wp.float64)
        self._candidate_normal = z((B, V), wp.vec3d)
        self.pose = {name: z(B, wp.mat33d if "rotation" in name else wp.vec3d) for name in _POSE}
        self.move_away(np.arange(B))
        self.indenters = [(int(kind), tuple(float(d) for d in dims)) for kind, dims in indenters]
        self._kind = arr(np.array([kind for kind, _ in self.indenters], dtype=np.int32), wp.int32)
        self._dims = arr(np.array([dims for _, dims in self.indenters], dtype=np.float64), wp.vec4d)
        pattern = BlockPattern.from_connectivities([tri, stencils, np.arange(V)[:, None]], V)
        use_cg = linear == "cg" or (linear == "auto" and wp.get_device(device).is_cuda)
        self.linear = (
            BatchedCG(BatchedBlockMatrix(pattern, B, self.free, device), 2 * B, warm=np.arange(2 * B) >= B)
            if use_cg
            else BatchedDirectSolver(pattern, B, self.free)
        )
        """Newton's linear algebra, chosen by the device: batched CG on a GPU (block matrix on the device),
        sparse direct per system on the CPU (host assembly); both `assemble`, `multiply` and `solve`. The CG
        starts K u2 = grad V (the smooth field block Jacobi converges slowest on, ~230 iterations at 0.5 mm
        edges against ~40 for K u1 = -r) from the system's last u2, which the next Newton step barely moves."""
        self._system_of = np.concatenate([np.arange(B), np.arange(B)]).astype(np.int32)
        self._system_of_b = wp.array(np.arange(B, dtype=np.int32), dtype=wp.int32, device=device)
        self._active = z(B, wp.int32)
        """Per system 1 where the current evaluation computes it (`evaluate`'s `which`)."""
        self.counters = dict.fromkeys(("evaluations", "evaluate_s", "linear_solves", "linear_solve_s"), 0.0)
        self.counters |= {"cg_iterations_max": 0.0, "cg_iterations_mean": 0.0, "system_evaluations": 0.0}
        """Work done so far: evaluations and their wall time (s), linear solves (assembly + CG) and their
        wall time, summed over solves the largest and the mean CG iteration count of the active columns, and
        the systems evaluated in Newton rounds (`evaluate_round`) summed over rounds."""

    # -- data movement ---------------------------------------------------------------------------
    def set_poses(
        self, rotation: np.ndarray, translation: np.ndarray, rotation_start: np.ndarray, translation_start: np.ndarray
    ) -> None:
        """Indenter poses (B,3,3) body->sensor and tip positions (B,3) m, now and at the increment's start."""
        for name, value in zip(_POSE, (rotation, translation, rotation_start, translation_start), strict=True):
            self.pose[name].assign(np.asarray(value, dtype=np.float64))

    def set_relaxation(
        self, rows: np.ndarray, scale: np.ndarray, frozen_stress: np.ndarray | None, angle_shift: np.ndarray | None
    ) -> None:
        """Viscoelastic terms of the coming solves of systems `rows` (`fe.viscoelastic`): membrane and bending
        moduli scaled by `scale` (k,) (1: elastic, 1 - g: fully relaxed), frozen membrane stresses (k,T,2,2)
        N/m and bending rest angles shifted by (k,n_bending,3) rad (None: none)."""
        rows = np.asarray(rows)
        static, params = self._static, [self.skins[i].params for i in rows]
        put_rows(static["mu_t"], rows, scale * np.array([p.membrane_modulus for p in params]))
        put_rows(static["bending_stiffness"], rows, scale * np.array([p.bending_stiffness for p in params]))
        k = len(rows)
        frozen = np.zeros((k, self.n_triangles, 2, 2)) if frozen_stress is None else frozen_stress
        shift = np.zeros((k, self.n_bending, 3)) if angle_shift is None else angle_shift
        put_rows(static["frozen_stress"], rows, frozen)
        if self.n_bending:
            put_rows(static["rest_angle"], rows, self._rest_angle + shift)

    def membrane_stress(self, x: np.ndarray, system: int) -> np.ndarray:
        """Elastic (instantaneous) membrane stress resultants (T,2,2) N/m of `system` at positions x (V,3) m."""
        p = self.skins[system].params
        return membrane.membrane_stress(x, self.skin.triangles, self._dm_inv, p.membrane_modulus, p.gent_inverse_jm)

    def bending_angle_change(self, x: np.ndarray) -> np.ndarray:
        """Dihedral-angle changes from the rest state (n_bending, 3) rad at positions x (V,3) m."""
        return bending.stencil_rest_state(x, self._stencils, self._present)[0] - self._rest_angle

    def move_away(self, rows: np.ndarray) -> None:
        """Put the indenters of systems `rows` 1 m off the skin (no contact until a pose is set) and clear their
        lagged friction forces."""
        k = len(rows)
        for name in _POSE:
            away = np.tile(np.eye(3), (k, 1, 1)) if "rotation" in name else np.tile([0.0, 0.0, 1.0], (k, 1))
            put_rows(self.pose[name], rows, away)
        put_rows(self.lagged_force, rows, np.zeros((k, self.n_vertices)))

    def set_skin(self, system: int, skin: InflatedSkin) -> None:
        """Give one system another skin of the batch's mesh (`per_system`), whose bending and relaxation the
        batch was built for (`later`; its starting state is the stepper's to install)."""
        per_system([self.skin, skin], 2)
        if (skin.params.bending and not self.n_bending) or (skin.params.relaxation_fraction > 0.0 and not self.relaxes):
            raise ValueError("a batch built without bending or relaxation cannot take a skin that has them")
        self.skins[system] = skin
        for name, value in _skin_values(skin).items():
            self._static[name][system : system + 1].assign(np.array([value]))
        self.air.boyle_constant[system] = skin.air_boyle

    def set_indenter(self, system: int, kind: int, dims: tuple[float, float, float, float]) -> None:
        """Give one system another indenter (kind, dims of `fe.indenter_sdf`)."""
        self.indenters[system] = (int(kind), tuple(float(d) for d in dims))
        self._kind[system : system + 1].assign(np.array([kind], dtype=np.int32))
        self._dims[system : system + 1].assign(np.array([dims], dtype=np.float64))

    # -- evaluation ------------------------------------------------------------------------------
    def evaluate(
        self, x: wp.array, want_hessian: bool, pressure: np.ndarray, which: np.ndarray | None = None
    ) -> BatchLinearization:
        """All energy terms of the systems in `which` (B,) bool (default all) at positions x (B,V) (m), their
        free-DOF residual at `pressure` (B,) Pa (in `self.residual`, with grad E in `self.gradient` and grad V
        in `self.bvec`). The kernels skip the other systems: their scalars come back 0 and their gradients
        0, their Hessians and residual rows are left as they were."""
        B, V, buf = self.batch, self.n_vertices, self.buf
        start = time.perf_counter()
        active = np.ones(B, dtype=bool) if which is None else np.asarray(which, dtype=bool)
        self._active.assign(active.astype(np.int32))
        self.gradients.zero_()
        for name in ("volume_gradient", "core_energy", "core_hessian", "indenter_energy", "indenter_hessian"):
            buf[name].zero_()
        buf["indenter_vertex_force"].zero_()
        common = {"x": x, "want_hessian": 1 if want_hessian else 0, "active": self._active}
        self._launch(membrane.membrane_kernel, self.n_triangles, common)
        if self.n_bending:
            self._launch(bending.bending_kernel, self.n_bending, common)
        self._launch(volume.volume_kernel, self.n_triangles, common)
        if self.has_core:
            self._launch(contact.core_contact_kernel, V, common)
        self._launch(contact.indenter_surface_kernel, self.n_triangles, common)
        friction = {"x_start": self.x_start, "lagged_force": self.lagged_force, "lagged_normal": self.lagged_normal}
        self._launch(contact.indenter_friction_kernel, V, common | friction)
        self._totals.zero_()  # per system: volume (m^3) and energy (J), summed on the device, fetched once
        self._launch(bk.totals, max(buf[name].shape[1] for name in _TOTALS), common | {"out": self._totals})
        self._stats.zero_()
        outputs = {"residual": self.residual, "gradient": self.gradient, "bvec": self.bvec, "stats": self._stats}
        outputs |= {"gradients": self.gradients, "pressure": self._per_system("pressure", pressure)}
        self._launch(bk.free_residual, V, common | outputs)
        stats, totals = self._stats.numpy(), self._totals.numpy()
        self.counters["evaluations"] += 1
        self.counters["evaluate_s"] += time.perf_counter() - start
        energy = totals[:, 1] + self.air.legendre_energy(pressure)
        liquid = totals[:, 0] - self.air.volume(pressure)
        return BatchLinearization(energy, liquid, stats[:, 0].copy(), np.sqrt(stats[:, 1]), stats[:, 2].copy())

    def proximity(self, x: wp.array, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Gap (k,V) m of each skin vertex (negative inside the contact band) and unit SDF normals (k,V,3) of x
        to each indenter, the smallest gap over every skin triangle's quadrature points (k,) m (negative: the
        surface contact acts, whatever the vertices' gaps), and the largest change (k,) m of a quadrature
        point's gap as each indenter moves from its start pose to its pose (`set_poses`), among the points in
        contact at either (`fe.contact.indenter_face_gap_kernel`), for the systems `rows` (k,) (the shell's
        gap buffers then hold all B systems' values)."""
        buf = self.buf
        self._launch(contact.indenter_gap_kernel, self.n_vertices, {"x": x})
        self._launch(contact.indenter_face_gap_kernel, self.n_triangles, {"x": x})
        face_gap = get_rows(buf["indenter_face_gap"], rows).min(axis=1)
        moved = get_rows(buf["indenter_face_moved"], rows).max(axis=1)
        return get_rows(buf["indenter_gap"], rows), get_rows(buf["indenter_normal"], rows), face_gap, moved

    def indenter_clearance(self, parts: wp.array, floor: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Nearest approach (m) of each `which` system's (B,) bool indenter body to the rigid core at its pose,
        (B,): exact to the sampling of `fe.contact.indenter_clearance_kernel` (core triangles split in
        `parts` (T_core,) per edge) where below `floor` (B,) m, a lower bound at least `floor` elsewhere;
        +inf for the other systems."""
        clearance = wp.full(self.batch, np.inf, dtype=wp.float64, device=self.device)
        values = {"parts": parts, "clearance": clearance, "floor": self._per_system("floor", floor)}
        self._launch(contact.indenter_clearance_kernel, len(parts), values | {"active": self._flags(which)})
        return clearance.numpy()

    def indenter_skin_clearance(
        self, x: wp.array, spacing: np.ndarray, floor: np.ndarray, which: np.ndarray
    ) -> np.ndarray:
        """Nearest approach (m, the indenter SDF; negative inside its body) of each `which` system's (B,) bool
        indenter body to each of its skin's mid-surface triangles at positions x (B,V), (B,T): sampled on
        the triangle with nodes at most `spacing` (B,) m apart where its bound is below `floor` (B,) m
        (`fe.contact.indenter_skin_clearance_kernel`), a lower bound at least `floor` elsewhere; +inf for the
        other systems."""
        clearance = wp.full((self.batch, self.n_triangles), np.inf, dtype=wp.float64, device=self.device)
        values = {"clearance": clearance, "x": x, "active": self._flags(which)}
        values |= {"spacing": self._per_system("spacing", spacing), "floor": self._per_system("floor", floor)}
        self._launch(contact.indenter_skin_clearance_kernel, self.n_triangles, values)
        return clearance.numpy()

    def _launch(self, kernel: wp.Kernel, count: int, values: dict) -> None:
        """One launch of `kernel` for every system and each of `count` items (skin vertices, triangles, ...),
        taking its arguments by name from `values`, else from the shell's per-system and mesh data (`_static`),
        its buffers (`buf`) and each system's own indenter shape and pose."""
        values = {**self._static, **self.buf, **self.pose, "kind": self._kind, "dims": self._dims, **values}
        launch(kernel, (self.batch, count), values, self.device)

    # -- Newton ------------------------------------------------------------------------------------
    def lag_contact(self, x: wp.array, mask: np.ndarray) -> np.ndarray:
        """Refresh the lagged friction forces and normals of the masked systems from positions x where they
        changed by more than the friction tolerance (per vertex: the surface contact's forces at x lumped to
        it, `fe.contact.lag_candidates`); returns which systems changed ((B,) bool)."""
        force = self._lag_buf["indenter_vertex_force"]
        force.zero_()
        self._lag_buf["indenter_gradient"].zero_()
        surface = {**self._lag_buf, "x": x, "want_hessian": 0, "active": self._flags(mask)}  # no Hessian written
        self._launch(contact.indenter_surface_kernel, self.n_triangles, surface)
        self._stats.zero_()
        values = {"vertex_force": force, "lagged_force": self.lagged_force, "candidate": self._candidate}
        values |= {"candidate_normal": self._candidate_normal, "stats": self._stats}
        launch(contact.lag_candidates, (self.batch, self.n_vertices), values, self.device)
        stats = self._stats.numpy()
        changed = mask & (stats[:, 0] > self.skin.contact.friction_tolerance * np.maximum(stats[:, 1], 1e-12))
        if changed.any():
            lagged = (self.lagged_force, self.lagged_normal)
            self._launch_vertices(bk.lag_apply, self._flags(changed), self._candidate, self._candidate_normal, *lagged)
        return changed

    def begin(self, state: NewtonBatch, which: np.ndarray, pressure: np.ndarray) -> None:
        """Start Newton for the systems in `which` (B,) bool from the positions in `self.x` and their
        `pressure` (B,) Pa: iteration 0, no friction refreshes yet, evaluated at x in the next round."""
        which = np.asarray(which, dtype=bool)
        state.pressure[which] = np.asarray(pressure, dtype=np.float64)[which]
        state.running |= which
        names = ("converged", "failed", "refreshed", "iterations", "passes", "last_eta", "phase", "step", "dp")
        for name in (*names, "attempt", "factorized", "chord_failed", "has_hessian"):
            getattr(state, name)[which] = 0
        state.last_residual[which] = np.nan
        for i in np.flatnonzero(which):
            state.message[i] = ""

    def evaluate_round(self, state: NewtonBatch) -> BatchLinearization:
        """One evaluation of every system where it stands: at its positions, or, in a line search or a chord
        step, at its trial point x + step dq with pressure p + step dp (in `self.x_trial`).

        With a linear solver that factorises (the CPU), trial points are evaluated without Hessians, which
        an accepted trial then gets in a round of its own if it needs a new matrix (few systems, the
        Hessians dominate the cost); otherwise every evaluation carries them, so an accepted trial's serves
        as the next Newton evaluation (many systems on a GPU, rounds dominate)."""
        running = state.running
        step = np.where(running & (state.phase != AT_X), state.step, 0.0)
        self.counters["system_evaluations"] += int(running.sum())
        self._axpy(self.x, step, self.x_trial)
        pressure = state.pressure + np.where(step != 0.0, step * state.dp, 0.0)
        hessians = not self.linear.holds_factorization or bool(np.any(running & (state.phase == AT_X)))
        state.has_hessian[running] = hessians
        return self.evaluate(self.x_trial, hessians, pressure, running)

    def settle(self, state: NewtonBatch, lin: BatchLinearization) -> np.ndarray:
        """Decide the line-search trials just evaluated (the acceptance rules of the backtracking, one
        trial per round): accepted systems move there, the others shorten their step (`_backtrack`), and a
        search that runs out of backtracks goes on with the residual norm, then with the next damping.
        Returns the running systems evaluated at their (possibly new) positions, ready for `check` and
        `iterate`."""
        at_x = state.running & (state.phase == AT_X)
        searching = state.running & (state.phase != AT_X)
        if not searching.any():
            return at_x
        cv = lin.volume - state.target
        phi = lin.energy - state.new_p * cv + 0.5 * state.rho * cv * cv
        energy_ok = np.isfinite(phi) & (phi <= state.phi0 + 1e-4 * state.step * state.slope)
        residual_ok = lin.residual_2 < (1.0 - 1e-4 * state.step) * state.rnorm
        chord_ok = lin.residual_inf <= self.skin.newton.chord_contraction * state.rnorm
        ok = np.select([state.phase == ENERGY_SEARCH, state.phase == CHORD], [energy_ok, chord_ok], residual_ok)
        accepted = searching & ok
        self._axpy(self.x, np.where(accepted, state.step, 0.0), self.x)
        state.pressure[accepted] += state.step[accepted] * state.dp[accepted]
        state.phase[accepted], state.attempt[accepted] = AT_X, 0
        state.chord_failed[accepted] = False
        chord_rejected = searching & ~accepted & (state.phase == CHORD)
        state.chord_failed |= chord_rejected
        state.phase[chord_rejected], state.step[chord_rejected] = AT_X, 0.0  # evaluated at x again next round
        state.has_hessian[chord_rejected] = False
        searching &= ~chord_rejected
        rejected = searching & ~accepted
        state.backtracks[rejected] += 1
        state.step[:] = _backtrack(state, phi, rejected)
        exhausted = rejected & (state.backtracks >= self.skin.newton.max_backtracks)
        to_residual = exhausted & (state.phase == ENERGY_SEARCH)
        state.phase[to_residual], state.step[to_residual], state.backtracks[to_residual] = RESIDUAL_SEARCH, 1.0, 0
        self._retry(state, exhausted & ~to_residual)
        return at_x | accepted

    def round(self, state: NewtonBatch) -> np.ndarray:
        """One Newton round of every running system (`evaluate_round`, `settle`, `check`, `iterate`): returns
        the systems that stopped in it, whose final evaluation the shell's buffers still hold."""
        lin = self.evaluate_round(state)
        at_x = self.settle(state, lin)
        stopped = self.check(state, lin, any(s.params.friction > 0.0 for s in self.skins), at_x)
        if state.running.any():
            self.iterate(state, lin, at_x)
        return stopped

    def check(self, state: NewtonBatch, lin: BatchLinearization, friction: bool, at_x: np.ndarray) -> np.ndarray:
        """The stopping rules (`fe.params.NewtonSettings`) for the running systems evaluated at their
        positions (`at_x`): refresh lagged friction near convergence (`friction`), then stop systems that
        converged, failed or reached the iteration limit. Returns the systems that stopped now ((B,) bool);
        their residual and volume are recorded in `state`."""
        settings, before = self.skin.newton, state.running.copy()
        running = state.running
        finite = np.isfinite(lin.residual_2) & np.isfinite(lin.residual_inf)  # a sum keeps NaN; atomic_max drops it
        finite &= np.isfinite(lin.energy) & np.isfinite(lin.volume)
        _finish(at_x & ~finite, running, state.message, "non-finite residual")
        _finish(at_x & state.failed, running, state.message, "line search failed")
        here = at_x & running
        tol = _tolerance(lin, settings)
        state.refreshed[:] = False
        if friction:
            near = here & (lin.residual_inf <= settings.refresh_factor * tol)
            near &= state.passes < self.skin.contact.friction_passes
            if near.any():
                state.refreshed[:] = self.lag_contact(self.x, near)
                state.passes += near
        c = lin.volume - state.target
        scale = np.where(state.target != 0.0, np.abs(state.target), 1.0)
        done = here & ~state.refreshed & (lin.residual_inf <= tol) & (np.abs(c) <= settings.volume_tolerance * scale)
        state.converged |= done
        _finish(done, running, state.message, "converged")
        _finish(here & (state.iterations >= settings.max_iterations), running, state.message, "iteration limit")
        stopped = before & ~running
        state.residual[stopped] = lin.residual_inf[stopped]
        state.volume[stopped] = lin.volume[stopped]
        state.phase[stopped] = AT_X
        return stopped

    def iterate(self, state: NewtonBatch, lin: BatchLinearization, at_x: np.ndarray) -> None:
        """A Newton direction for every running system evaluated at its positions (`at_x`) whose friction was
        not just refreshed, damped per its `attempt`, all in one linear solve, and its line search set up
        (the trials are evaluated by the next rounds). A system whose direction is unusable tries the next
        damping in the next round (with everyone else's solve, not in an extra one of its own); one that
        runs out of dampings fails."""
        here = state.running & at_x
        stepping = here & ~state.refreshed
        c = lin.volume - state.target
        near = lin.residual_inf <= self.skin.newton.refresh_factor * _tolerance(lin, self.skin.newton)
        chord = stepping & near & state.factorized & ~state.chord_failed & (state.attempt == 0)
        if chord.any():
            stepping &= ~self._chord(state, lin, c, chord)
        stale = stepping & ~state.has_hessian  # evaluated at x without Hessians: again, with them, next round
        state.phase[stale], state.step[stale] = AT_X, 0.0
        stepping &= ~stale
        fresh = here & ~stale & (state.attempt == 0)  # a retry with damping belongs to the iteration it retries
        if stepping.any():
            eta = self._forcing(state, lin)
            damping = np.where(stepping, _DAMPING[np.minimum(state.attempt, len(_DAMPING) - 1)], 0.0)
            dp, ok = self._direction(state.pressure, c, stepping, damping, eta)
            curvature = self._curvature(stepping)
            ok &= (curvature > 0.0) | ((state.attempt > 0) & (c != 0.0))
            self._start_search(state, lin, c, dp, curvature, stepping & ok)
            self._retry(state, stepping & ~ok)
            usable = stepping & ok
            state.factorized[usable] = self.linear.holds_factorization
            state.chord_failed[usable] = False
            state.last_residual[usable], state.last_eta[usable] = lin.residual_inf[usable], eta[usable]
        state.iterations[fresh] += 1

    def _chord(self, state: NewtonBatch, lin: BatchLinearization, c: np.ndarray, which: np.ndarray) -> np.ndarray:
        """Chord steps for the systems in `which`: the bordered Newton system solved with the factorisation
        the linear solver holds from an earlier iterate (no assembly, no factorisation), tried at full length
        in the next round (`settle` keeps it when the residual falls by `chord_contraction`). Returns the
        systems that got one; the others are marked as having failed a chord here."""
        self._launch_vertices(bk.newton_rhs, self.residual, self.bvec, self.rhs)
        u, _, solved = self.linear.resolve(self.rhs, self._system_of, np.concatenate([which, which]))
        dp, ok = self._bordered(u, solved, c, state.pressure, which)
        state.chord_failed |= which & ~ok
        state.dp[ok], state.rnorm[ok] = dp[ok], lin.residual_inf[ok]
        state.phase[ok], state.step[ok] = CHORD, 1.0
        return ok

    def _retry(self, state: NewtonBatch, which: np.ndarray) -> None:
        """The systems in `which` found no step: back at their positions with the next damping, or failed."""
        state.attempt[which] += 1
        state.failed |= which & (state.attempt >= len(_DAMPING))
        state.phase[which], state.step[which] = AT_X, 0.0

    def _start_search(
        self,
        state: NewtonBatch,
        lin: BatchLinearization,
        c: np.ndarray,
        dp: np.ndarray,
        curvature: np.ndarray,
        which: np.ndarray,
    ) -> None:
        """Set up the backtracking line search along (self.dq, dp) for the systems in `which`:
        on the merit function E - p_new (V - V0) + rho/2 (V - V0)^2 where its slope is resolved, else on the
        residual norm; the first trial is the full step."""
        cc = np.where(c != 0.0, c * c, 1.0)
        rho = np.where((state.attempt > 0) & (c != 0.0), 3.0 * np.maximum(0.0, -curvature) / cc, 0.0)
        new_p = state.pressure + dp
        phi0 = lin.energy - new_p * c + 0.5 * rho * c * c
        grad_dq, bvec_dq = self._two_dots(self.dq, self.gradient, self.bvec)
        slope = grad_dq - new_p * bvec_dq
        slope -= rho * c * c
        energy = -slope > _ENERGY_RESOLUTION * np.maximum(np.abs(phi0), np.abs(lin.energy))
        for name, value in (("dp", dp), ("new_p", new_p), ("rho", rho), ("phi0", phi0), ("slope", slope)):
            getattr(state, name)[which] = value[which]
        state.rnorm[which] = lin.residual_2[which]
        state.phase[which] = np.where(energy, ENERGY_SEARCH, RESIDUAL_SEARCH)[which]
        state.step[which], state.backtracks[which] = 1.0, 0

    def _forcing(self, state: NewtonBatch, lin: BatchLinearization) -> np.ndarray:
        """Relative CG tolerances (B,) of the next Newton step. "strict": a linear residual of 1 % of the
        Newton tolerance, whatever the residual (eta = 1e-2 tol / |r|, within 1e-10 ... 1e-3). "adaptive":
        Eisenstat and Walker's choice 2 (SIAM J. Sci. Comput. 17, 1996), eta = 0.9 (|r| / |r_prev|)^2,
        safeguarded by 0.9 eta_prev^2, within `NewtonSettings.min_forcing` ... 0.1 (the first step of a solve:
        0.1), and never asking for a linear residual below half the Newton tolerance: solves are loose far from
        the solution."""
        tol, residual = _tolerance(lin, self.skin.newton), np.maximum(lin.residual_inf, 1e-300)
        if self.forcing == "strict":
            return np.clip(1e-2 * tol / residual, 1e-10, 1e-3)
        first = ~np.isfinite(state.last_residual)
        ratio = residual / np.where(first, 1.0, np.maximum(state.last_residual, 1e-300))
        eta = 0.9 * ratio**2
        safeguard = 0.9 * state.last_eta**2
        eta = np.where(safeguard > 0.1, np.maximum(eta, safeguard), eta)
        eta = np.where(first, _ETA_MAX, np.clip(eta, self.skin.newton.min_forcing, _ETA_MAX))
        return np.clip(np.maximum(eta, 0.5 * tol / residual), 1e-10, _ETA_MAX)

    def _direction(
        self, pressure: np.ndarray, c: np.ndarray, mask: np.ndarray, damping: np.ndarray, eta: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Assemble K = H_E - p H_V (+ damping), solve K u1 = -r, K u2 = b (`self.linear`); dq of the masked
        systems (in self.dq; the other rows keep theirs) and dp (B,)."""
        buf, start = self.buf, time.perf_counter()
        families = {"membrane": 0, "bending": 1, "core": 2, "indenter": 2}  # triangles, stencils, vertices
        terms = [(family, buf[f"{name}_hessian"], None) for name, family in families.items()]
        self.linear.assemble([*terms, (0, buf["volume_hessian"], -pressure)], damping, mask)
        self._launch_vertices(bk.newton_rhs, self.residual, self.bvec, self.rhs)
        active = np.concatenate([mask, mask])
        u, iterations, state = self.linear.solve(
            self.rhs, self._system_of, active, np.concatenate([eta, eta]), self.cg_max_iterations
        )
        self.counters["linear_solves"] += 1
        self.counters["linear_solve_s"] += time.perf_counter() - start
        self.counters["cg_iterations_max"] += float(iterations[active].max())
        self.counters["cg_iterations_mean"] += float(iterations[active].mean())
        return self._bordered(u, state, c, pressure, mask)

    def _bordered(
        self, u: wp.array, solved: np.ndarray, c: np.ndarray, pressure: np.ndarray, mask: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The bordered Newton step from the solutions u (2B, V) of K u1 = -r, K u2 = b (column states
        `solved`): dp = -(c + b.u1) / (b.u2 + s) with the trapped air's compliance s (m^3/Pa), dq = u1 + dp u2
        into self.dq for the masked systems whose solve worked; returns dp (B,) and that mask."""
        B = self.batch
        ok = mask & (solved[:B] != CG_NEGATIVE_CURVATURE) & (solved[B:] != CG_NEGATIVE_CURVATURE)
        bu2, bu1 = self._two_dots(self.bvec, u[B:], u[:B])
        schur = bu2 + self.air.compliance(pressure)
        ok &= np.isfinite(schur) & (schur != 0.0)
        dp = np.where(ok, -(c + bu1) / np.where(ok, schur, 1.0), 0.0)
        self._launch_vertices(bk.combine, u, self._per_system("dp", dp), self._flags(mask), self.dq)
        return dp, ok

    def _two_dots(self, x: wp.array, a: wp.array, b: wp.array) -> tuple[np.ndarray, np.ndarray]:
        """Per system x . a and x . b ((B,) each) of (B, V) vec3d arrays, in one launch."""
        self._pair.zero_()
        wp.launch(bk.two_dots, x.shape, [x, a, b, self._pair], device=self.device)
        pair = self._pair.numpy()
        return pair[:, 0].copy(), pair[:, 1].copy()

    def _curvature(self, mask: np.ndarray) -> np.ndarray:
        """dq . K dq per system (with the damping of the last assembly)."""
        self.linear.multiply(self.dq, self.kdq, self._system_of_b)
        return np.where(mask, self._two_dots(self.dq, self.kdq, self.kdq)[0], 0.0)

    def _axpy(self, x: wp.array, step: np.ndarray, out: wp.array) -> None:
        """out = x + step dq per system (rows with step 0 copied from x, whatever dq holds)."""
        self._launch_vertices(bk.axpy, x, self._per_system("step", step), self.dq, out)

    def _launch_vertices(self, kernel: wp.Kernel, *args: wp.array) -> None:
        """Launch `kernel` over every (system, skin vertex) with the positional arguments `args`."""
        wp.launch(kernel, (self.batch, self.n_vertices), list(args), device=self.device)

    def _flags(self, mask: np.ndarray) -> wp.array:
        """(B,) int32 flags of a boolean mask, in a device array reused between calls."""
        return self._per_system("flags", mask, np.int32)

    def _per_system(self, name: str, values: np.ndarray, dtype: type = np.float64) -> wp.array:
        """(B,) per-system values in the device scratch array `name` (kept between calls; each launch
        argument takes its own name)."""
        scratch = self._scratch.get(name)
        if scratch is None:
            scratch = self._scratch[name] = wp.zeros(self.batch, dtype=wp.dtype_from_numpy(dtype), device=self.device)
        scratch.assign(np.asarray(values, dtype=dtype))
        return scratch


_TOTALS = ("volume", "membrane_energy", "bending_energy", "core_energy", "indenter_energy", "indenter_face_energy")
"""The per-element buffers summed into `BatchedShell._totals` (per system: volume, energy)."""
_POSE = ("rotation", "translation", "rotation_start", "translation_start")


def _indexed(array: wp.array, rows: np.ndarray) -> wp.indexedarray:
    """The `rows` of `array` (along its first axis) as one indexed view on the array's device."""
    return wp.indexedarray(array, [wp.array(np.asarray(rows, dtype=np.int32), dtype=wp.int32, device=array.device)])


def put_rows(array: wp.array, rows: np.ndarray, values: np.ndarray) -> None:
    """array[i] = values[k] for the k-th system index i of `rows` (distinct rows): one host -> device copy and
    one scatter on the device."""
    _indexed(array, rows).assign(np.ascontiguousarray(values))


def get_rows(array: wp.array, rows: np.ndarray) -> np.ndarray:
    """array[rows] on the host, shape (len(rows), ...); rows not empty, in any order, repeats allowed: one gather
    on the device and one device -> host copy."""
    return _indexed(array, rows).numpy()


def _backtrack(state: NewtonBatch, phi: np.ndarray, rejected: np.ndarray) -> np.ndarray:
    """Next trial steps (B,) after rejections: on the energy merit function the minimiser of the quadratic
    through phi0, its slope and the rejected trial phi(t), kept within [0.1 t, 0.5 t] (Dennis and
    Schnabel, Numerical Methods for Unconstrained Optimization, 6.3.2), so that a step far too long is cut
    in one round, not in many halvings; on the residual norm, t / 2."""
    t = state.step
    curvature = phi - state.phi0 - state.slope * t
    usable = np.isfinite(curvature) & (curvature > 0.0)
    quadratic = -state.slope * t * t / (2.0 * np.where(usable, curvature, 1.0))
    quadratic = np.where(usable, quadratic, 0.1 * t)
    energy = np.clip(quadratic, 0.1 * t, 0.5 * t)
    return np.where(rejected, np.where(state.phase == ENERGY_SEARCH, energy, 0.5 * t), t)


def _tolerance(lin: BatchLinearization, settings: NewtonSettings) -> np.ndarray:
    """Residual tolerance (B,) N of each system: absolute, or relative to its largest nodal load."""
    return np.maximum(settings.force_tolerance, settings.relative_force_tolerance * lin.load)


def _finish(which: np.ndarray, running: np.ndarray, message: list[str], text: str) -> None:
    """Stop the systems in `which`, recording why."""
    for i in np.flatnonzero(which & running):
        message[i] = text
    running &= ~which
