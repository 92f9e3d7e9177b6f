"""Quasi-linear viscoelasticity (Prony series) of the skin's membrane and bending, as an incremental potential.

Fung's QLV: the stress is a hereditary integral of the elastic (instantaneous, "glassy") stress sigma_e,
sigma(t) = integral G(t - s) d sigma_e(s), with the reduced relaxation function
G(t) = g_inf + sum_i g_i exp(-t / tau_i), g_inf = 1 - sum_i g_i. Branch i carries the internal stress
h_i(t) = integral g_i exp(-(t - s) / tau_i) d sigma_e(s), so sigma = g_inf sigma_e + sum_i h_i, and over a
step dt with sigma_e linear in time (exact for a constant or a linearly ramped elastic stress):

    h_i <- exp(-dt / tau_i) h_i + g_i gamma_i (sigma_e,new - sigma_e,old),  gamma_i = (1 - exp(-x)) / x, x = dt / tau_i.

Within a step sigma = c sigma_e(x) + a with the constants c = g_inf + sum_i g_i gamma_i and
a = sum_i (exp(-dt / tau_i) h_i - g_i gamma_i sigma_e,old): the gradient of c W_e + a : (strain), so each
increment stays an energy minimisation (symmetric Hessian, Newton unchanged).
- Membrane: sigma_e is the second Piola-Kirchhoff stress resultant N_e = 2 dW_e/dC (N/m, per triangle in
  its reference frame); the frozen part adds (1/2) a : (C - I) per reference area (`fe.membrane.membrane_kernel`).
- Bending: the energy is quadratic in the dihedral-angle changes dtheta, sigma_e = K dtheta with a constant
  K, so the branches live in angle space and the increment is the elastic bending energy scaled by c about
  rest angles shifted by -a / c: no extra kernel.
The fully relaxed (long-term) state is dt -> infinity: c = g_inf, a = 0; inflation uses it (the sensor
has sat inflated for long), and `SkinRelaxation.reset` starts the branches relaxed (h_i = 0) there.
"""

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from fe.batched import BatchedShell


def step_factors(fractions: np.ndarray, times: np.ndarray, dt: float | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per branch: decay exp(-dt / tau_i) and weight g_i gamma_i of the elastic stress change over dt (s; one
    for every branch, or one per branch)."""
    if np.any(np.asarray(dt) < 0):
        raise ValueError(f"time step {dt} s must be non-negative")
    x = dt / times
    with np.errstate(divide="ignore", invalid="ignore"):
        gamma = np.where(x > 0.0, -np.expm1(-x) / x, 1.0)
    return np.exp(-x), fractions * gamma


class SkinRelaxation:
    """Prony-series state of the B systems of a `fe.batched.BatchedShell`, one branch each (fraction g and
    time tau in s, (B,) arrays; g = 0: elastic), driven increment by increment for chosen systems (`rows`).

    Call `prepare(rows, dt)` before solving increments that end dt (s) after the last accepted states (it
    installs their scaled moduli, frozen membrane stresses and shifted bending rest angles into the shell)
    and `advance(rows, dt, x)` once they converged at positions x (k,V,3) m.
    """

    def __init__(self, shell: "BatchedShell", fractions: np.ndarray, times: np.ndarray) -> None:
        fractions, times = np.asarray(fractions, dtype=float), np.asarray(times, dtype=float)
        if fractions.shape != (shell.batch,) or times.shape != (shell.batch,):
            raise ValueError("one Prony fraction and one relaxation time per system")
        if np.any(fractions < 0) or np.any(fractions >= 1.0) or np.any(times <= 0):
            raise ValueError("Prony fractions must be in [0, 1), relaxation times > 0")
        self.shell, self.fractions, self.times = shell, fractions, times
        self.long_term = 1.0 - fractions
        n_tri, n_bend = shell.n_triangles, shell.n_bending
        self.membrane = np.zeros((shell.batch, n_tri, 2, 2))
        """Internal membrane stress h (B,T,2,2) N/m of each system's branch."""
        self.membrane_elastic = np.zeros((shell.batch, n_tri, 2, 2))
        """Elastic membrane stress (B,T,2,2) N/m at the last accepted state."""
        self.bending = np.zeros((shell.batch, n_bend, 3))
        """Internal bending 'stress' h (B,n_bending,3) in angle space (rad)."""
        self.bending_elastic = np.zeros((shell.batch, n_bend, 3))
        """Dihedral-angle changes (B,n_bending,3) rad at the last accepted state."""

    def reset(self, rows: np.ndarray, x: np.ndarray) -> None:
        """Systems `rows` fully relaxed at positions x (k,V,3) m (h = 0), at their long-term moduli."""
        self.membrane[rows], self.bending[rows] = 0.0, 0.0
        for k, i in enumerate(rows):
            self.membrane_elastic[i] = self.shell.membrane_stress(x[k], i)
            self.bending_elastic[i] = self.shell.bending_angle_change(x[k])
        self.shell.set_relaxation(rows, self.long_term[rows], None, None)

    def at_rest(self, rows: np.ndarray) -> np.ndarray:
        """(k,) whether no branch of systems `rows` holds internal stress (the state `reset` leaves)."""
        held = np.abs(self.membrane[rows]).reshape(len(rows), -1).max(axis=1, initial=0.0) > 0.0
        held |= np.abs(self.bending[rows]).reshape(len(rows), -1).max(axis=1, initial=0.0) > 0.0
        return ~held

    def prepare(self, rows: np.ndarray, dt: np.ndarray) -> None:
        """Install the algorithmic moduli of steps of dt (k,) s into systems `rows`: scale c = g_inf + g gamma,
        frozen membrane stress a = decay h - g gamma N_e,old, bending rest angles shifted by -a_bend / c."""
        decay, weight = step_factors(self.fractions[rows], self.times[rows], np.asarray(dt, dtype=float))
        scale = self.long_term[rows] + weight
        d4, w4 = decay[:, None, None, None], weight[:, None, None, None]
        frozen = d4 * self.membrane[rows] - w4 * self.membrane_elastic[rows]
        frozen_angle = d4[..., 0] * self.bending[rows] - w4[..., 0] * self.bending_elastic[rows]
        self.shell.set_relaxation(rows, scale, frozen, -frozen_angle / scale[:, None, None])

    def advance(self, rows: np.ndarray, dt: np.ndarray, x: np.ndarray) -> None:
        """Accept steps of dt (k,) s of systems `rows` that converged at positions x (k,V,3) m."""
        decay, weight = step_factors(self.fractions[rows], self.times[rows], np.asarray(dt, dtype=float))
        for k, i in enumerate(rows):
            stress, angles = self.shell.membrane_stress(x[k], i), self.shell.bending_angle_change(x[k])
            self.membrane[i] = decay[k] * self.membrane[i] + weight[k] * (stress - self.membrane_elastic[i])
            self.bending[i] = decay[k] * self.bending[i] + weight[k] * (angles - self.bending_elastic[i])
            self.membrane_elastic[i], self.bending_elastic[i] = stress, angles
