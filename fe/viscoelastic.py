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
  its reference frame); the frozen part adds (1/2) a : (C - I) per reference area (`frozen_stress_kernel`).
- Bending: the energy is quadratic in the dihedral-angle changes dtheta, sigma_e = K dtheta with a constant
  K, so the branches live in angle space and the increment is the elastic bending energy scaled by c about
  rest angles shifted by -a / c: no extra kernel.
The fully relaxed (long-term) state is dt -> infinity: c = g_inf, a = 0; inflation uses it (the sensor
has sat inflated for long), and `SkinRelaxation.reset` starts the branches relaxed (h_i = 0) there.
"""

from typing import TYPE_CHECKING

import numpy as np
import warp as wp

from fe.membrane import deformation_gradient, edge_gradient
from fe.wptypes import mat32d, mat99d

if TYPE_CHECKING:
    from fe.shell import ShellSystem


@wp.kernel
def frozen_stress_kernel(
    x: wp.array2d(dtype=wp.vec3d),
    triangles: wp.array(dtype=wp.vec3i),
    dm_inv: wp.array(dtype=wp.mat22d),
    rest_area: wp.array(dtype=wp.float64),
    stress: wp.array(dtype=wp.mat22d),
    want_hessian: int,
    energy: wp.array2d(dtype=wp.float64),
    gradient: wp.array2d(dtype=wp.vec3d),
    hessian: wp.array2d(dtype=mat99d),
):
    """Adds (1/2) A0 a : (C - I) per (batch, triangle), a = `stress` (N/m, symmetric), to the membrane's
    energy, node gradients (P = A0 F a) and 9x9 Hessian (dP = A0 dF a); run after `membrane_kernel`."""
    b, t = wp.tid()
    tri = triangles[t]
    Dinv = dm_inv[t]
    F = deformation_gradient(x, b, tri, Dinv)
    a = stress[t]
    area = rest_area[t]
    strain = wp.transpose(F) @ F - wp.identity(n=2, dtype=wp.float64)
    energy[b, t] = energy[b, t] + wp.float64(0.5) * area * wp.trace(a @ strain)
    P = area * (F @ a)
    for n in range(3):
        wp.atomic_add(gradient, b, tri[n], P @ edge_gradient(n, Dinv))
    if want_hessian != 0:
        H = hessian[b, t]
        for nb in range(3):
            gb = edge_gradient(nb, Dinv)
            for j in range(3):
                dF = mat32d()
                dF[j, 0] = gb[0]
                dF[j, 1] = gb[1]
                dP = area * (dF @ a)
                for na in range(3):
                    col = dP @ edge_gradient(na, Dinv)
                    for i in range(3):
                        H[3 * na + i, 3 * nb + j] = H[3 * na + i, 3 * nb + j] + col[i]
        hessian[b, t] = H


def step_factors(fractions: np.ndarray, times: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Per branch: decay exp(-dt / tau_i) and weight g_i gamma_i of the elastic stress change over dt (s)."""
    if dt < 0:
        raise ValueError(f"time step {dt} s must be non-negative")
    x = dt / times
    with np.errstate(divide="ignore", invalid="ignore"):
        gamma = np.where(x > 0.0, -np.expm1(-x) / x, 1.0)
    return np.exp(-x), fractions * gamma


class BranchHistory:
    """Internal stresses h_i (branch, *shape) of the Prony branches for one generalised stress, and the
    elastic stress sigma_e at the last accepted state."""

    def __init__(self, n_branches: int, elastic_stress: np.ndarray) -> None:
        self.elastic_stress = elastic_stress.copy()
        self.internal = np.zeros((n_branches, *elastic_stress.shape))

    def frozen(self, decay: np.ndarray, weight: np.ndarray) -> np.ndarray:
        """a = sum_i (decay_i h_i - weight_i sigma_e,old): the stress held constant through the coming step."""
        return np.tensordot(decay, self.internal, axes=1) - weight.sum() * self.elastic_stress

    def advance(self, decay: np.ndarray, weight: np.ndarray, elastic_stress: np.ndarray) -> None:
        """Accept the step: h_i <- decay_i h_i + weight_i (sigma_e,new - sigma_e,old)."""
        change = elastic_stress - self.elastic_stress
        self.internal = decay.reshape(-1, *[1] * change.ndim) * self.internal
        self.internal += weight.reshape(-1, *[1] * change.ndim) * change
        self.elastic_stress = elastic_stress.copy()


class SkinRelaxation:
    """Prony-series state of one `ShellSystem` (fractions g_i, times tau_i in s) driven step by step.

    Call `prepare(dt)` before solving an increment that ends dt seconds after the last accepted state (it
    installs the increment's scaled moduli, frozen membrane stress and shifted bending rest angles into the
    system) and `advance(dt, x)` once it converged at positions x (V,3) m.
    """

    def __init__(self, system: "ShellSystem", fractions: np.ndarray, times: np.ndarray) -> None:
        fractions, times = np.asarray(fractions, dtype=float), np.asarray(times, dtype=float)
        if fractions.shape != times.shape or fractions.ndim != 1:
            raise ValueError("one relaxation time per Prony fraction")
        if np.any(fractions < 0) or fractions.sum() >= 1.0 or np.any(times <= 0):
            raise ValueError("Prony fractions must be >= 0 with sum < 1, relaxation times > 0")
        self.system, self.fractions, self.times = system, fractions, times
        self.long_term = 1.0 - float(fractions.sum())

    def reset(self, x: np.ndarray) -> None:
        """Fully relaxed at positions x (V,3) m (h_i = 0), the system set to its long-term moduli."""
        n = len(self.fractions)
        self.membrane = BranchHistory(n, self.system.membrane_stress(x))
        self.bending = BranchHistory(n, self.system.bending_angle_change(x))
        self.system.set_relaxation(self.long_term)

    @property
    def at_rest(self) -> bool:
        """Whether no branch holds internal stress (the state `reset` leaves)."""
        return not (self.membrane.internal.any() or self.bending.internal.any())

    def prepare(self, dt: float) -> None:
        """Install the algorithmic moduli of a step of dt (s) into the system."""
        decay, weight = step_factors(self.fractions, self.times, dt)
        scale = self.long_term + float(weight.sum())
        self.system.set_relaxation(
            scale, self.membrane.frozen(decay, weight), -self.bending.frozen(decay, weight) / scale
        )

    def advance(self, dt: float, x: np.ndarray) -> None:
        """Accept a step of dt (s) that converged at positions x (V,3) m."""
        decay, weight = step_factors(self.fractions, self.times, dt)
        self.membrane.advance(decay, weight, self.system.membrane_stress(x))
        self.bending.advance(decay, weight, self.system.bending_angle_change(x))
