"""Quasi-static, displacement-controlled indentation of a pressurised shell by a rigid indenter.

The indenter translates along a fixed direction in steps; each increment re-solves equilibrium with the
fluid volume held, warm-started from the last one, with friction lagged (normal forces and normals
refreshed between Newton solves until they settle). Forces are in newtons in the sensor frame and are
the force the indenter applies to the skin.
"""

import time
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from fe.newton import NewtonSettings, solve_equilibrium
from fe.shell import IndenterState, ShellSystem, lumped_areas


@dataclass(frozen=True)
class IncrementResult:
    """Outputs of one increment (SI units, sensor frame)."""

    depth: float
    """Indenter travel past first contact (m)."""
    force: np.ndarray
    """(3,) force of the indenter on the skin (N)."""
    pressure: float
    """Fluid pressure (Pa)."""
    volume: float
    """Enclosed volume (m^3) as the skin triangles measure it."""
    contact_area: float
    """Deformed area of skin vertices in contact with the indenter (m^2)."""
    contact_radius: float
    """Largest distance of a contact vertex from the indenter axis through the first-touch point (m)."""
    displacement: np.ndarray
    """(V,3) nodal displacements from the reference (inflated) state (m)."""
    newton_iterations: int
    residual: float
    """Infinity norm of the free-DOF residual force (N)."""
    equilibrium_error: float
    """|indenter + core + anchor + pressure forces on the skin| / max(|indenter|, |pressure| force)."""
    converged: bool
    message: str
    wall_s: float


@dataclass(frozen=True)
class Trajectory:
    """A straight indentation: first-touch tip position (m), unit direction, depths past touch (m)."""

    touch_point: np.ndarray
    direction: np.ndarray
    rotation: np.ndarray
    depths: np.ndarray

    def __post_init__(self) -> None:
        if np.any(np.asarray(self.depths) < 0):
            raise ValueError("indentation depths must be non-negative")
        if not np.isclose(np.linalg.norm(self.direction), 1.0):
            raise ValueError("direction must be a unit vector")


def _force_balance(system: ShellSystem, terms: dict, pressure: float) -> tuple[np.ndarray, float]:
    """Indenter force on the skin (N) and the relative error of the global force balance."""
    residual = terms["elastic_gradient"] + terms["core_gradient"] + terms["indenter_gradient"]
    residual = residual - pressure * terms["volume_gradient"]
    anchors = np.where(system.fixed_dofs, residual, 0.0).sum(axis=0)
    f_indenter = -terms["indenter_gradient"].sum(axis=0)
    f_core = -terms["core_gradient"].sum(axis=0)
    f_pressure = pressure * terms["volume_gradient"].sum(axis=0)
    imbalance = np.linalg.norm(f_indenter + f_core + f_pressure + anchors)
    scale = max(np.linalg.norm(f_indenter), np.linalg.norm(f_pressure), 1e-300)
    return f_indenter, float(imbalance / scale)


def indent(
    system: ShellSystem,
    x_reference: np.ndarray,
    pressure_reference: float,
    target_volume: float,
    kind: int,
    dims: tuple[float, float, float, float],
    trajectory: Trajectory,
    offset: float,
    newton: NewtonSettings = NewtonSettings(),
) -> Iterator[IncrementResult]:
    """Yield one result per depth; stop after the first increment that does not converge."""
    x, pressure = x_reference.copy(), pressure_reference
    translation = trajectory.touch_point.copy()
    axis_point = trajectory.touch_point
    cs = system.contact_settings
    for depth in trajectory.depths:
        start = time.perf_counter()
        system.x_start = x.copy()
        new_translation = trajectory.touch_point + depth * trajectory.direction
        system.indenter = IndenterState(kind, dims, trajectory.rotation, new_translation, translation, offset)
        iterations, q = 0, system.free_coordinates(x)
        system.lagged_force[:] = 0.0
        for _ in range(cs.friction_passes):
            terms = system.evaluate(system.positions(q), want_hessian=False)
            force = cs.penalty_stiffness * system.vertex_area * np.maximum(-terms["indenter_gap"], 0.0)
            change = np.max(np.abs(force - system.lagged_force), initial=0.0)
            if iterations and change <= cs.friction_tolerance * max(force.max(initial=0.0), 1e-12):
                break
            system.lagged_force = force
            system.lagged_normal = terms["indenter_normal"]
            result = solve_equilibrium(system, q, pressure, target_volume, newton)
            iterations += result.iterations
            q, pressure = result.q, result.pressure
            if not result.converged or system.params.friction == 0.0:
                break
        x = system.positions(q)
        translation = new_translation
        terms = system.evaluate(x, want_hessian=False)
        f_indenter, balance = _force_balance(system, terms, pressure)
        in_contact = terms["indenter_gap"] < 0.0
        rel = x - axis_point
        radial = rel - np.outer(rel @ trajectory.direction, trajectory.direction)
        yield IncrementResult(
            depth=float(depth),
            force=f_indenter,
            pressure=float(pressure),
            volume=float(terms["volume"]),
            contact_area=float(lumped_areas(x, system.mesh.triangles)[in_contact].sum()),
            contact_radius=float(np.linalg.norm(radial[in_contact], axis=1).max(initial=0.0)),
            displacement=x - x_reference,
            newton_iterations=iterations,
            residual=result.residual_norm,
            equilibrium_error=balance,
            converged=result.converged,
            message=result.message,
            wall_s=time.perf_counter() - start,
        )
        if not result.converged:
            return
