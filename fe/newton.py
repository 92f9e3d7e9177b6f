"""Newton's method for quasi-static equilibrium with an optional enclosed-volume constraint.

Solves grad E(x) - p grad V(x) = 0 and V(x) = V_target for the free positions x (m) and the fluid
pressure p (Pa), the Lagrange multiplier of the volume constraint. Each step solves the bordered KKT
system [[K, -b], [-b^T, 0]] through its Schur complement with a sparse direct factorisation of K
(`fe.linsolve`), where K is the Hessian of E minus p
times the volume Hessian, and backtracks on an augmented-Lagrangian merit function. K is the exact
Hessian (quadratic convergence near a stable equilibrium); an iteration whose exact step shows
non-positive curvature, or finds no acceptable step length, is redone with per-element PSD-projected
energy Hessians (robust, but only linearly convergent).
"""

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import scipy.sparse as sp

from fe.linsolve import SingularMatrixError, SymmetricSolver


@dataclass
class Linearization:
    """Energy (J), its gradient (N), volume (m^3), volume gradient (m^2), KKT matrix block K (N/m), and the
    derivative of the constrained volume with respect to the pressure (m^3/Pa; a trapped gas's compliance)."""

    energy: float
    gradient: np.ndarray
    volume: float
    volume_gradient: np.ndarray
    matrix: sp.csr_matrix | None
    volume_compliance: float = 0.0


class EquilibriumProblem(Protocol):
    """What Newton needs from a model: values, gradients and Hessians at free positions `q` (m), and a
    factorisation object kept across solves (its symbolic analysis is reused).

    With `projected` the energy Hessian blocks are projected to PSD element by element.
    """

    linear_solver: SymmetricSolver

    def linearize(
        self, q: np.ndarray, pressure: float, want_matrix: bool, projected: bool = False
    ) -> Linearization: ...


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
    refresh_factor: float = 1e5
    """Lagged quantities are refreshed, and chord steps tried, once the residual is below refresh_factor x
    its tolerance."""
    chord_contraction: float = 0.2
    """A chord step (last factorisation reused) is kept when it cuts the residual by at least this factor."""


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


_ENERGY_RESOLUTION = 1e-12
"""Relative size below which energy differences are round-off (sums over thousands of elements)."""


def _dot(a: np.ndarray, b: np.ndarray) -> float:
    """a . b of two vectors without BLAS: numpy's threaded OpenBLAS dot costs ~8 ms CPU for 10^4 entries
    on a loaded 2-core machine (thread wake-ups), einsum's own loop ~10 us."""
    return float(np.einsum("i,i->", a, b))


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
    refresh: Callable[[np.ndarray], bool] | None = None,
) -> NewtonResult:
    """Newton-solve from (q0, pressure0). With `target_volume` None the pressure is held fixed instead.

    `refresh(q)`, when given, updates lagged data of the problem (e.g. friction normal forces) near
    convergence and returns whether they changed beyond their tolerance; a solve only converges once
    they have settled.

    Near convergence (residual below `refresh_factor` x its tolerance) an iteration first tries a chord
    step with the last factorisation (one solve and one gradient evaluation, no Hessian); it is kept when
    it shrinks the residual by at least `chord_contraction`, else the iteration is a full Newton step.
    """
    q, pressure = q0.copy(), float(pressure0)
    lin = problem.linearize(q, pressure, want_matrix=True)
    volume_scale = abs(target_volume) if target_volume else 1.0
    factorized = False  # the solver holds a factorisation of this solve's matrix at a recent state
    for iteration in range(settings.max_iterations + 1):
        r = _residual(lin, pressure)
        rnorm = _inf_norm(r)
        c = 0.0 if target_volume is None else lin.volume - target_volume
        if on_iteration is not None:
            on_iteration(iteration, rnorm)
        if not np.isfinite(rnorm):
            return NewtonResult(q, pressure, False, iteration, rnorm, lin.volume, "non-finite residual")
        tolerance = _force_tolerance(lin, pressure, settings)
        near = rnorm <= settings.refresh_factor * tolerance
        if refresh is not None and near and refresh(q):
            lin = problem.linearize(q, pressure, want_matrix=False)
            continue
        if rnorm <= tolerance and abs(c) <= settings.volume_tolerance * volume_scale:
            return NewtonResult(q, pressure, True, iteration, rnorm, lin.volume, "converged")
        if iteration == settings.max_iterations:
            break
        if factorized and near:
            chord = _chord_step(problem, lin, q, pressure, r, c, target_volume is not None, rnorm, settings)
            if chord is not None:
                q, pressure, lin = chord
                continue
        if lin.matrix is None:
            lin = problem.linearize(q, pressure, want_matrix=True)
        step = _line_search(problem, lin, q, pressure, r, c, target_volume, settings, robust=False)
        if step is None:
            projected = problem.linearize(q, pressure, want_matrix=True, projected=True)
            step = _line_search(problem, projected, q, pressure, r, c, target_volume, settings, robust=True)
        if step is None:
            return NewtonResult(q, pressure, False, iteration, rnorm, lin.volume, "line search failed")
        q, pressure, lin = step
        if lin is None:
            lin = problem.linearize(q, pressure, want_matrix=False)
        factorized = True
    r = _residual(lin, pressure)
    rnorm = _inf_norm(r)
    return NewtonResult(q, pressure, False, settings.max_iterations, rnorm, lin.volume, "iteration limit")


def _chord_step(
    problem: EquilibriumProblem,
    lin: Linearization,
    q: np.ndarray,
    pressure: float,
    r: np.ndarray,
    c: float,
    constrained: bool,
    rnorm: float,
    settings: NewtonSettings,
) -> tuple[np.ndarray, float, Linearization] | None:
    """A Newton step with the factorisation already held by the solver (the matrix of an earlier iterate):
    the new (q, pressure, linearization without matrix) when it cuts the residual's infinity norm by
    `chord_contraction`, else None."""
    dq, dp = _solve_bordered(problem.linear_solver, lin, r, c, constrained)
    if dq is None:
        return None
    trial = problem.linearize(q + dq, pressure + dp, want_matrix=False)
    trial_r = _residual(trial, pressure + dp)
    trial_norm = _inf_norm(trial_r)
    if not trial_norm <= settings.chord_contraction * rnorm:
        return None
    return q + dq, pressure + dp, trial


def _inf_norm(r: np.ndarray) -> float:
    """Largest absolute entry of a residual (0 for an empty one)."""
    return float(np.max(np.abs(r), initial=0.0))


def _force_tolerance(lin: Linearization, pressure: float, settings: NewtonSettings) -> float:
    """Residual force tolerance (N): absolute floor or a part-per-million of the largest nodal load."""
    load = max(np.max(np.abs(lin.gradient), initial=0.0), np.max(np.abs(pressure * lin.volume_gradient), initial=0.0))
    return max(settings.force_tolerance, settings.relative_force_tolerance * load)


def _line_search(
    problem: EquilibriumProblem,
    lin: Linearization,
    q: np.ndarray,
    pressure: float,
    r: np.ndarray,
    c: float,
    target_volume: float | None,
    settings: NewtonSettings,
    robust: bool,
) -> tuple[np.ndarray, float, Linearization | None] | None:
    """Newton step with backtracking on the merit function: new (q, pressure) and the linearization there
    (without matrix; None where it was evaluated at another pressure), or None when the matrix is singular,
    has non-positive curvature along the step (unless `robust`), or no step length is acceptable."""
    dq, dp = _newton_step(lin, r, c, target_volume is not None, problem.linear_solver)
    if dq is None:
        return None
    new_pressure = pressure + dp
    curvature = _dot(dq, lin.matrix @ dq)
    if not curvature > 0.0 and not (robust and c != 0.0):
        return None
    # Along dq the slope of the Lagrangian at the new pressure is -curvature; where that is not negative
    # (robust mode only) a quadratic penalty on the volume error restores descent.
    rho = 3.0 * max(0.0, -curvature) / (c * c) if c != 0.0 else 0.0
    phi0 = _merit(lin, new_pressure, target_volume, rho)
    slope = _dot(_residual(lin, new_pressure), dq) - rho * c * c
    if -slope > _ENERGY_RESOLUTION * max(abs(phi0), abs(lin.energy)):
        step = 1.0
        for _ in range(settings.max_backtracks):
            trial = problem.linearize(q + step * dq, new_pressure, want_matrix=False)
            phi = _merit(trial, new_pressure, target_volume, rho)
            if np.isfinite(phi) and phi <= phi0 + 1e-4 * step * slope:
                # The trial was evaluated at the full step's pressure: reusable only for a full step.
                return q + step * dq, pressure + step * dp, trial if step == 1.0 else None
            step *= 0.5
    # The energy cannot resolve this step (round-off near the solution) or no step decreased it: backtrack
    # on the Euclidean norm of the residual force, for which the Newton step is a descent direction too.
    rnorm, step = np.sqrt(_dot(r, r)), 1.0
    for _ in range(settings.max_backtracks):
        trial = problem.linearize(q + step * dq, pressure + step * dp, want_matrix=False)
        trial_r = _residual(trial, pressure + step * dp)
        if np.sqrt(_dot(trial_r, trial_r)) < (1.0 - 1e-4 * step) * rnorm:
            return q + step * dq, pressure + step * dp, trial
        step *= 0.5
    return None


def _newton_step(
    lin: Linearization, r: np.ndarray, c: float, constrained: bool, solver: SymmetricSolver
) -> tuple[np.ndarray | None, float]:
    """Factorise lin.matrix and solve the (bordered) Newton system; returns (dq, dp) or (None, 0) when singular."""
    try:
        solver.factorize(lin.matrix)
    except SingularMatrixError:
        return None, 0.0
    return _solve_bordered(solver, lin, r, c, constrained)


def _solve_bordered(
    solver: SymmetricSolver, lin: Linearization, r: np.ndarray, c: float, constrained: bool
) -> tuple[np.ndarray | None, float]:
    """Solve the bordered Newton system for (dq, dp) with the factorisation of K that `solver` holds (not
    necessarily of lin.matrix: chord steps reuse an earlier one); (None, 0) when singular.

    Through the Schur complement: with K u1 = -r and K u2 = b (b = lin.volume_gradient),
    dq = u1 + dp u2 and dp = -(c + b.u1) / (b.u2 + s) (s: `volume_compliance`).
    """
    try:
        if not constrained:
            return solver.solve(-r), 0.0
        b = lin.volume_gradient
        u = solver.solve(np.column_stack([-r, b]))
    except SingularMatrixError:
        return None, 0.0
    schur = _dot(b, u[:, 1]) + lin.volume_compliance
    if not (np.isfinite(schur) and schur != 0.0):
        return None, 0.0
    dp = -(c + _dot(b, u[:, 0])) / schur
    return u[:, 0] + dp * u[:, 1], dp
