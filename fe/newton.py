"""Newton's stopping rules and step controls for quasi-static equilibrium with a held enclosed volume.

The engine (`fe.batched.BatchedShell`) solves grad E(x) - p grad V(x) = 0 and V(x) = V_target for the free
positions x (m) and the fluid pressure p (Pa), the Lagrange multiplier of the volume constraint, each step
through the bordered KKT system's Schur complement, backtracking on an augmented-Lagrangian merit function.
"""

from dataclasses import dataclass


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
