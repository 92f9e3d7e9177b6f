"""Newton's method for quasi-static equilibrium with an optional enclosed-volume constraint.

Solves grad E(x) - p grad V(x) = 0 and V(x) = V_target for the free positions x (m) and the fluid
pressure p (Pa), the Lagrange multiplier of the volume constraint. Each step solves the bordered KKT
system [[K, -b], [-b^T, 0]] with a sparse direct factorisation, where K is the PSD-projected Hessian of
E minus p times the volume Hessian, and backtracks on an augmented-Lagrangian merit function.
"""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


@dataclass
class Linearization:
    """Energy (J), its gradient (N), volume (m^3), volume gradient (m^2), KKT matrix block K (N/m)."""

    energy: float
    gradient: np.ndarray
    volume: float
    volume_gradient: np.ndarray
    matrix: sp.csr_matrix | None


class EquilibriumProblem(Protocol):
    """What Newton needs from a model: values, gradients and Hessians at free positions `q` (m)."""

    def linearize(self, q: np.ndarray, pressure: float, want_matrix: bool) -> Linearization: ...


@dataclass(frozen=True)
class NewtonSettings:
    """Stopping rules: residual force (infinity norm), relative volume error, iteration cap.

    The residual must fall below max(force_tolerance (N), relative_force_tolerance x the largest nodal
    load |grad E| or |p grad V|), i.e. a part-per-million balance of every node's forces by default.
    """

    force_tolerance: float = 1e-10
    relative_force_tolerance: float = 1e-6
    volume_tolerance: float = 1e-10
    max_iterations: int = 60
    max_backtracks: int = 30


@dataclass
class NewtonResult:
    """Converged (or last) free positions (m), pressure (Pa) and how the solve went."""

    q: np.ndarray
    pressure: float
    converged: bool
    iterations: int
    residual_norm: float
    volume: float
    message: str


def _residual(lin: Linearization, pressure: float) -> np.ndarray:
    return lin.gradient - pressure * lin.volume_gradient


def _merit(lin: Linearization, pressure: float, target: float | None, rho: float) -> float:
    if target is None:
        return lin.energy - pressure * lin.volume
    c = lin.volume - target
    return lin.energy - pressure * c + 0.5 * rho * c * c


def solve_equilibrium(
    problem: EquilibriumProblem,
    q0: np.ndarray,
    pressure0: float,
    target_volume: float | None,
    settings: NewtonSettings = NewtonSettings(),
    on_iteration: Callable[[int, float], None] | None = None,
) -> NewtonResult:
    """Newton-solve from (q0, pressure0). With `target_volume` None the pressure is held fixed instead."""
    q, pressure = q0.copy(), float(pressure0)
    lin = problem.linearize(q, pressure, want_matrix=True)
    volume_scale = abs(target_volume) if target_volume else 1.0
    for iteration in range(settings.max_iterations + 1):
        r = _residual(lin, pressure)
        rnorm = float(np.max(np.abs(r))) if r.size else 0.0
        c = 0.0 if target_volume is None else lin.volume - target_volume
        if on_iteration is not None:
            on_iteration(iteration, rnorm)
        if not np.isfinite(rnorm):
            return NewtonResult(q, pressure, False, iteration, rnorm, lin.volume, "non-finite residual")
        load = max(
            np.max(np.abs(lin.gradient), initial=0.0), np.max(np.abs(pressure * lin.volume_gradient), initial=0.0)
        )
        tolerance = max(settings.force_tolerance, settings.relative_force_tolerance * load)
        if rnorm <= tolerance and abs(c) <= settings.volume_tolerance * volume_scale:
            return NewtonResult(q, pressure, True, iteration, rnorm, lin.volume, "converged")
        if iteration == settings.max_iterations:
            break
        dq, dp = _newton_step(lin, r, c, target_volume is not None)
        if dq is None:
            return NewtonResult(q, pressure, False, iteration, rnorm, lin.volume, "singular KKT matrix")
        new_pressure = pressure + dp
        curvature = float(dq @ (lin.matrix @ dq))
        rho = 3.0 * max(0.0, -curvature) / (c * c) if c != 0.0 else 0.0
        phi0 = _merit(lin, new_pressure, target_volume, rho)
        slope = float(_residual(lin, new_pressure) @ dq) - rho * c * c
        step, accepted = 1.0, False
        for _ in range(settings.max_backtracks):
            trial = problem.linearize(q + step * dq, new_pressure, want_matrix=False)
            phi = _merit(trial, new_pressure, target_volume, rho)
            if np.isfinite(phi) and (phi <= phi0 + 1e-4 * step * min(slope, 0.0) or slope >= 0.0 and phi <= phi0):
                accepted = True
                break
            step *= 0.5
        if not accepted:
            # Near the solution the merit function stalls at round-off; accept a full step that still
            # reduces the residual force.
            step = 1.0
            trial = problem.linearize(q + dq, new_pressure, want_matrix=False)
            if not np.max(np.abs(_residual(trial, new_pressure)), initial=0.0) < rnorm:
                return NewtonResult(q, pressure, False, iteration, rnorm, lin.volume, "line search failed")
        q = q + step * dq
        pressure = pressure + step * dp
        lin = problem.linearize(q, pressure, want_matrix=True)
    r = _residual(lin, pressure)
    rnorm = float(np.max(np.abs(r))) if r.size else 0.0
    return NewtonResult(q, pressure, False, settings.max_iterations, rnorm, lin.volume, "iteration limit")


def _newton_step(lin: Linearization, r: np.ndarray, c: float, constrained: bool) -> tuple[np.ndarray | None, float]:
    """Solve the (bordered) Newton system; returns (dq, dp) or (None, 0) when singular."""
    K = lin.matrix
    try:
        if not constrained:
            lu = spla.splu(K.tocsc(), permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
            return lu.solve(-r), 0.0
        b = lin.volume_gradient[:, None]
        kkt = sp.bmat([[K, sp.csr_matrix(-b)], [sp.csr_matrix(-b.T), None]], format="csc")
        lu = spla.splu(kkt, permc_spec="MMD_AT_PLUS_A", options={"SymmetricMode": True})
        sol = lu.solve(np.concatenate([-r, [c]]))
    except RuntimeError:
        return None, 0.0
    if not np.all(np.isfinite(sol)):
        return None, 0.0
    return sol[:-1], float(sol[-1])
