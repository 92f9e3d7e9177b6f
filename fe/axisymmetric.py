"""Axisymmetric reference solution for the inflated, indented hemispherical membrane ("Dome").

Independent of the warp finite-element code: pure numpy/scipy, used to check the 3D shell model.

Problem
-------
A hemispherical incompressible Neo-Hookean membrane (reference radius ``R``, thickness ``t``, shear
modulus ``mu``; strain energy per unit reference area
``W = (mu t / 2)(l1^2 + l2^2 + 1/(l1^2 l2^2) - 3)``) is pinned at its equator to the rigid plane
``z = 0``.  The cavity is filled with incompressible fluid: it is first inflated to
``V = volume_ratio * 2/3 pi R^3`` (uniform pressure ``p``), then, with ``V`` held, a rigid frictionless
sphere of radius ``r_i`` is pushed coaxially onto the apex to depth ``d`` (``d = 0`` at first touch).

Method
------
Lagrangian axisymmetric membrane equations in the reference arc length ``S`` measured from the apex
(Yang & Feng 1970).  Lengths are scaled by ``R``, pressure by ``mu t / R``.  With the reference radius
``R0(S) = sin S``, the state is ``y = (r, z, theta, l1, V, E)``: the deformed radius and height, the
meridian tangent angle (``dr/dS = l1 cos theta``, ``dz/dS = -l1 sin theta``), the meridional stretch,
the enclosed volume and the strain energy accumulated from the apex.  ``l2 = r / R0``.  With
``W_i = dW/dl_i`` the tangential equilibrium ``d(R0 W_1)/dS = W_2 cos theta`` gives ``dl1/dS``; the
normal equilibrium gives ``dtheta/dS = (p l1 l2 - W_2 sin theta / R0) / W_1`` on the free membrane,
while in the contact zone the membrane lies on the sphere, ``dtheta/dS = -l1 / r_i`` (the contact
pressure ``q = p + (T1 + T2) / r_i`` is whatever closes normal equilibrium; no shear traction).
The membrane leaves the sphere tangentially (continuous theta; a kink would need the sphere to pull),
so the contact edge ``S_c`` is one more unknown.  Shooting from the apex (series start at ``S = 1e-5``,
``l1 = l2`` there) through the contact zone and the free membrane to the rim, on vectorised DOP853
integrations (rtol 1e-10):

* inflation: unknowns (apex stretch, p / p_sphere(apex stretch)), conditions ``r(pi/2) = 1`` and
  ``V = V_target``; Newton with a finite-difference Jacobian, continuation in volume.
* indentation: along the path parameter ``sigma = S_c + (apex stretch - inflated apex stretch)`` the
  unknowns (apex stretch, p) satisfy the same two conditions at fixed ``sigma`` (a well-conditioned 2x2
  Newton solve); the depth (drop of the apex below the inflated apex height) is an output, increasing
  along the path.  The path is continued from the inflated state until it brackets each requested
  depth, which is then hit by an Illinois-secant iteration on ``sqrt(depth)``.  (``sigma`` follows
  ``S_c`` while shallow, where the depth is ill-conditioned, and the apex stretch when the membrane wraps
  a small indenter and the contact edge stalls.)

The indenter force is the vertical equilibrium of the contact cap,
``F = p pi a^2 + 2 pi R0(S_c) W_1 sin(psi_c)``, with ``a = r(S_c)`` and ``psi_c = -theta(S_c)`` the
sphere's polar angle at the contact edge.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp

_S_APEX = 1.0e-5  # start of the integration, reference arc length / R
_S_RIM = 0.5 * math.pi  # reference arc length of the equator / R
_RTOL = 1.0e-10
_ATOL = 1.0e-12
_NEWTON_TOL = 1.0e-10  # residuals are dimensionless; the integration noise floor is ~1e-10
_NEWTON_MAXITER = 15
_FD_STEP = 1.0e-7
_N_STATE = 6
_INFLATION_START = 1.1  # first continuation point in V / V0 (below ~1.01 it is ill-conditioned)
_INFLATION_STEP = 0.5  # continuation step in V / V0
_EDGE_STEP = 0.03  # largest continuation step in the path parameter (see indent_dome)
_EDGE_STEP_MIN = 1.0e-4  # smallest continuation step in the path parameter before giving up
_EDGE_TOL = 1.0e-12  # bracket width in the path parameter that ends the depth search
_DEPTH_TOL = 1.0e-9  # tolerance on sqrt(depth / R) in the depth search
_FIRST_CONTACT_EDGE = 0.02  # path parameter (~ S_c, reference arc length / R) of the first contact solve


@dataclass(frozen=True)
class DomeState:
    """One equilibrium of the dome benchmark (SI units).

    Attributes:
        depth: indenter travel from first touch with the inflated apex (m).
        force: axial force of the sphere on the membrane, positive pushing down (N).
        pressure: fluid pressure (Pa).
        volume: fluid volume enclosed by membrane and base (m^3).
        contact_radius: radial extent of the contact zone (m).
        strain_energy: elastic energy stored in the membrane (J).
        rim_force: axial force with which the membrane pulls up on the base along its rim (N);
            vertical equilibrium requires ``rim_force = pressure * pi R^2 - force``.
    """

    depth: float
    force: float
    pressure: float
    volume: float
    contact_radius: float
    strain_energy: float = 0.0
    rim_force: float = 0.0


@dataclass(frozen=True)
class _Shot:
    """Dimensionless end values of a batch of shootings (arrays over the batch)."""

    rim_radius: np.ndarray
    apex_height: np.ndarray
    volume: np.ndarray
    energy: np.ndarray
    contact_radius: np.ndarray
    force: np.ndarray
    rim_angle: np.ndarray
    rim_force: np.ndarray


def _rhs(s: np.ndarray, y: np.ndarray, p: np.ndarray, curvature: float | None) -> np.ndarray:
    """Derivative d y / dS of the membrane state (dimensionless), batched over columns.

    Args:
        s: reference arc length per column.
        y: state, shape (6, n): r, z, theta, l1, volume, energy.
        p: pressure per column (units of mu t / R).
        curvature: 1 / indenter radius (in 1/R) in the contact zone, ``None`` on the free membrane.
    """
    r, _, th, l1 = y[0], y[1], y[2], y[3]
    r0 = np.sin(s)
    dr0 = np.cos(s)
    l2 = r / r0
    inv = 1.0 / (l1 * l2)
    w1 = l1 - inv * inv / l1
    w2 = l2 - inv * inv / l2
    w11 = 1.0 + 3.0 * inv * inv / (l1 * l1)
    w12 = 2.0 * inv**3
    c, sn = np.cos(th), np.sin(th)
    d = np.empty_like(y)
    d[0] = l1 * c
    d[1] = -l1 * sn
    if curvature is None:
        d[2] = (p * l1 * l2 - w2 * sn / r0) / w1
    else:
        d[2] = -l1 * curvature
    d[3] = (w2 * c - dr0 * w1 - w12 * (l1 * c - l2 * dr0)) / (r0 * w11)
    d[4] = math.pi * r * r * l1 * sn
    d[5] = math.pi * r0 * (l1 * l1 + l2 * l2 + inv * inv - 3.0)
    return d


def _phase(y0: np.ndarray, s0: np.ndarray, s1: np.ndarray, p: np.ndarray, curvature: float | None) -> np.ndarray:
    """Integrate all columns of ``y0`` from ``S = s0`` to ``S = s1`` (per column); return the end state."""
    n = y0.shape[1]
    span = s1 - s0

    def fun(tau: float, yflat: np.ndarray) -> np.ndarray:
        y = yflat.reshape(_N_STATE, n)
        return (_rhs(s0 + span * tau, y, p, curvature) * span).ravel()

    sol = solve_ivp(fun, (0.0, 1.0), y0.ravel(), method="DOP853", rtol=_RTOL, atol=_ATOL)
    if not sol.success:
        raise RuntimeError(f"membrane integration failed: {sol.message}")
    return sol.y[:, -1].reshape(_N_STATE, n)


def _apex_state(stretch: np.ndarray, curvature: np.ndarray) -> np.ndarray:
    """Series start at ``S = _S_APEX``: locally a spherical cap of the given curvature, isotropic stretch."""
    arc = stretch * _S_APEX
    angle = curvature * arc
    small = np.abs(angle) < 1e-12
    safe = np.where(small, 1.0, curvature)
    y = np.zeros((_N_STATE, stretch.size))
    y[0] = np.where(small, arc, np.sin(angle) / safe)
    y[1] = np.where(small, 0.0, -(1.0 - np.cos(angle)) / safe)
    y[2] = angle
    y[3] = stretch
    y[5] = 0.5 * math.pi * _S_APEX**2 * (2.0 * stretch**2 + stretch**-4 - 3.0)
    return y


def _shoot(stretch: np.ndarray, s_contact: np.ndarray, p: np.ndarray, curvature: float) -> _Shot:
    """Shoot from the apex to the equator for a batch of (apex stretch, contact edge S_c, pressure).

    ``S_c = 0`` for every column means no contact (inflation); otherwise every ``S_c > _S_APEX``.
    """
    if np.all(s_contact == 0.0):
        w1 = stretch - stretch**-5
        y = _apex_state(stretch, p * stretch / (2.0 * w1))
        s_free = np.full_like(p, _S_APEX)
    else:
        y = _apex_state(stretch, np.full_like(p, -curvature))
        y = _phase(y, np.full_like(p, _S_APEX), s_contact, p, curvature)
        s_free = s_contact
    r_c, th_c, l1_c = y[0].copy(), y[2].copy(), y[3].copy()
    end = _phase(y, s_free, np.full_like(p, _S_RIM), p, None)
    l2_c = r_c / np.sin(s_free)
    w1_c = l1_c - 1.0 / (l1_c**3 * l2_c**2)
    in_contact = s_contact > 0.0
    force = np.where(in_contact, math.pi * p * r_c**2 - 2.0 * math.pi * np.sin(s_free) * w1_c * np.sin(th_c), 0.0)
    l1_e, l2_e = end[3], end[0]  # at the rim R0 = 1, so l2 = r
    return _Shot(
        rim_radius=end[0],
        apex_height=-end[1],
        volume=end[4],
        energy=end[5],
        contact_radius=np.where(in_contact, r_c, 0.0),
        force=force,
        rim_angle=end[2],
        rim_force=2.0 * math.pi * (l1_e - 1.0 / (l1_e**3 * l2_e**2)) * np.sin(end[2]),
    )


def _newton(residual, x0: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Damped Newton with a forward-difference Jacobian; ``residual`` maps a batch (n, k) to (n, k).

    Each iterate is evaluated together with its finite-difference neighbours in one batch.  Converged
    when the largest residual is below ``_NEWTON_TOL``, or when the Newton step is at the integration
    noise floor (below 1e-11 of ``scale``) with residuals below 1e-8.
    """
    k = x0.size
    steps = _FD_STEP * scale

    def evaluate(x: np.ndarray) -> np.ndarray:
        batch = np.repeat(x[:, None], k + 1, axis=1)
        batch[np.arange(k), np.arange(1, k + 1)] += steps
        return residual(batch)

    x = x0.astype(float).copy()
    res = evaluate(x)
    if not np.all(np.isfinite(res)):
        raise RuntimeError("shooting failed at the initial guess")
    for _ in range(_NEWTON_MAXITER):
        f0 = res[:, 0]
        norm0 = np.max(np.abs(f0))
        if norm0 < _NEWTON_TOL:
            return x
        dx = np.linalg.solve((res[:, 1:] - f0[:, None]) / steps[None, :], -f0)
        if np.all(np.abs(dx) < 1e-11 * scale) and norm0 < 1e-8:
            return x
        alpha = 1.0
        while True:
            trial = x + alpha * dx
            res = evaluate(trial)
            if np.all(np.isfinite(res)) and np.max(np.abs(res[:, 0])) < norm0:
                break
            alpha *= 0.5
            if alpha < 0.03:
                raise RuntimeError("Newton line search failed in the shooting solve")
        x = trial
    raise RuntimeError("Newton did not converge in the shooting solve")


def _safe_shoot(stretch: np.ndarray, s_contact: np.ndarray, p: np.ndarray, curvature: float) -> _Shot | None:
    """``_shoot`` returning ``None`` when the trial leaves the physical range (it then is rejected)."""
    tiny_contact = (s_contact > 0.0) & (s_contact < 10.0 * _S_APEX)
    if np.any(stretch <= 0.0) or np.any(s_contact < 0.0) or np.any(s_contact >= _S_RIM) or np.any(tiny_contact):
        return None
    with np.errstate(all="ignore"):
        try:
            return _shoot(stretch, s_contact, p, curvature)
        except RuntimeError:
            return None


def _sphere_pressure(stretch: np.ndarray | float) -> np.ndarray | float:
    """Dimensionless pressure of a closed sphere inflated to ``stretch``: 2 (1/l - 1/l^7)."""
    return 2.0 * (1.0 / stretch - stretch**-7)


def _solve_inflation(volume: float) -> tuple[float, float, _Shot]:
    """Dimensionless inflated state at the given volume: (apex stretch, pressure, shot).

    Unknowns are the apex stretch and the pressure relative to that of a closed sphere at the apex stretch
    (close to 1 and well conditioned as the strain goes to 0).  Continuation in volume from the linear
    membrane solution (uniform strain (V/V0 - 1)/3) with linear extrapolation.
    """
    v0 = 2.0 * math.pi / 3.0

    def residual_at(target: float):
        def residual(x: np.ndarray) -> np.ndarray:
            shot = _safe_shoot(x[0], np.zeros(x.shape[1]), x[1] * _sphere_pressure(x[0]), 0.0)
            if shot is None:
                return np.full(x.shape, np.nan)
            return np.vstack([shot.rim_radius - 1.0, (shot.volume - target) / v0])

        return residual

    ratio_end = volume / v0
    ratio_start = min(ratio_end, _INFLATION_START)
    n_steps = int(math.ceil((ratio_end - ratio_start) / _INFLATION_STEP))
    ratios = np.linspace(ratio_start, ratio_end, n_steps + 1)
    history = [np.array([1.0 + (ratios[0] - 1.0) / 3.0, 1.0])]
    for ratio in ratios:
        guess = history[-1] if len(history) < 2 else 2.0 * history[-1] - history[-2]
        history.append(_newton(residual_at(ratio * v0), guess, np.array([1.0, 1.0])))
    lam, rel = history[-1]
    p = rel * _sphere_pressure(lam)
    return float(lam), float(p), _shoot(np.array([lam]), np.zeros(1), np.array([p]), 0.0)


def _check_sizes(**sizes: float) -> None:
    for name, value in sizes.items():
        if not (math.isfinite(value) and value > 0.0):
            raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def _check_ratio(volume_ratio: float) -> None:
    if not (math.isfinite(volume_ratio) and volume_ratio > 1.0):
        raise ValueError(f"volume_ratio must be a finite number > 1, got {volume_ratio!r}")


def _state(depth: float, shot: _Shot, p: float, radius: float, mu_t: float) -> DomeState:
    return DomeState(
        depth=depth,
        force=float(shot.force[0]) * mu_t * radius,
        pressure=p * mu_t / radius,
        volume=float(shot.volume[0]) * radius**3,
        contact_radius=float(shot.contact_radius[0]) * radius,
        strain_energy=float(shot.energy[0]) * mu_t * radius**2,
        rim_force=float(shot.rim_force[0]) * mu_t * radius,
    )


def inflate_dome(radius: float, thickness: float, mu: float, volume_ratio: float) -> DomeState:
    """Inflate the pinned hemispherical membrane to ``volume_ratio`` times its reference volume.

    Args:
        radius: reference radius R of the hemisphere (m).
        thickness: membrane thickness t (m).
        mu: shear modulus (Pa).
        volume_ratio: V / V0 with V0 = 2/3 pi R^3 (dimensionless, > 1).

    Returns:
        The inflated state: depth 0 (m), force 0 (N), pressure (Pa), volume (m^3), contact radius 0 (m).
    """
    _check_sizes(radius=radius, thickness=thickness, mu=mu)
    _check_ratio(volume_ratio)
    _, p, shot = _solve_inflation(volume_ratio * 2.0 * math.pi / 3.0)
    return _state(0.0, shot, p, radius, mu * thickness)


def indent_dome(
    radius: float,
    thickness: float,
    mu: float,
    volume_ratio: float,
    indenter_radius: float,
    depths: Sequence[float],
) -> list[DomeState]:
    """Push a rigid frictionless sphere onto the apex of the inflated dome at constant fluid volume.

    Args:
        radius: reference radius R of the hemisphere (m).
        thickness: membrane thickness t (m).
        mu: shear modulus (Pa).
        volume_ratio: inflation V / V0 with V0 = 2/3 pi R^3 (dimensionless, > 1), held during indentation.
        indenter_radius: radius of the rigid sphere (m).
        depths: indenter travels from first touch with the inflated apex (m, >= 0), any order.

    Returns:
        One ``DomeState`` per entry of ``depths`` (same order): force on the sphere (N, positive pushing
        down), fluid pressure (Pa), volume (m^3), contact radius (m), strain energy (J), rim force (N).

    Raises:
        ValueError: on non-positive sizes, ``volume_ratio <= 1`` or a negative depth.
        RuntimeError: when the shooting solve fails (e.g. a depth far beyond ~40 % of R).
    """
    _check_sizes(radius=radius, thickness=thickness, mu=mu, indenter_radius=indenter_radius)
    _check_ratio(volume_ratio)
    depth_list = [float(d) for d in depths]
    for d in depth_list:
        if not (math.isfinite(d) and d >= 0.0):
            raise ValueError(f"depths must be finite and >= 0, got {d!r}")
    mu_t = mu * thickness
    v0 = 2.0 * math.pi / 3.0
    target_volume = volume_ratio * v0
    curvature = radius / indenter_radius
    lam0, p0, shot0 = _solve_inflation(target_volume)
    h0 = float(shot0.apex_height[0])

    def edge(sigma: float, stretch: np.ndarray) -> np.ndarray:
        """Contact edge S_c (reference arc / R) on the path at parameter ``sigma``."""
        return sigma - (stretch - lam0)

    def solve_on_path(sigma: float, guess: np.ndarray) -> np.ndarray:
        """(apex stretch, p) of the equilibrium at path parameter ``sigma``."""

        def residual(x: np.ndarray) -> np.ndarray:
            shot = _safe_shoot(x[0], edge(sigma, x[0]), x[1], curvature)
            if shot is None:
                return np.full(x.shape, np.nan)
            return np.vstack([shot.rim_radius - 1.0, (shot.volume - target_volume) / v0])

        return _newton(residual, guess, np.ones(2))

    # Solution path with parameter sigma = S_c + (apex stretch - inflated apex stretch): sorted rows
    # (sigma, apex stretch, p, depth / R), starting at the inflated state.  The depth is an output,
    # increasing along the path.  sigma follows S_c for shallow indentation, where the depth is an
    # ill-conditioned parameter, and the apex stretch once the membrane wraps a small indenter and the
    # contact edge stalls.  New points are guessed by linear interpolation / extrapolation in sigma.
    path = [(0.0, lam0, p0, 0.0)]

    def add_point(sigma: float) -> float:
        rows = np.array(path)
        if len(path) == 1:
            guess = rows[0, 1:3]
        else:
            i = int(np.clip(np.searchsorted(rows[:, 0], sigma), 1, len(path) - 1))
            a, b = rows[i - 1], rows[i]
            guess = a[1:3] + (sigma - a[0]) / (b[0] - a[0]) * (b[1:3] - a[1:3])
        lam, p = solve_on_path(sigma, guess)
        shot = _shoot(np.array([lam]), edge(sigma, np.array([lam])), np.array([p]), curvature)
        depth = float(h0 - shot.apex_height[0])
        path.append((sigma, float(lam), float(p), depth))
        path.sort()
        return depth

    def advance(s_from: float, s_to: float) -> None:
        """Add the point at ``s_to``, through intermediate points if the direct solve fails."""
        try:
            add_point(s_to)
        except RuntimeError:
            if s_to - s_from < 2.0 * _EDGE_STEP_MIN:
                raise
            middle = 0.5 * (s_from + s_to)
            advance(s_from, middle)
            advance(middle, s_to)

    solved = {0.0: _state(0.0, shot0, p0, radius, mu_t)}
    for depth in sorted({d for d in depth_list if d > 0.0}):
        target = depth / radius
        # March along the path until it brackets the target depth.
        while path[-1][3] < target:
            s_last, _, _, d_last = path[-1]
            if len(path) == 1:
                s_next = _FIRST_CONTACT_EDGE
            else:
                s_prev, _, _, d_prev = path[-2]
                slope = (s_last - s_prev) / (math.sqrt(d_last) - math.sqrt(d_prev))
                s_pred = s_last + (math.sqrt(target) - math.sqrt(d_last)) * slope
                s_next = min(max(s_pred, s_last + 0.1 * _EDGE_STEP), s_last + _EDGE_STEP)
            if s_next >= _S_RIM:
                raise RuntimeError(f"depth {depth!r} m is beyond the reach of the solver")
            advance(s_last, s_next)
        # Illinois-secant on sqrt(depth) in sigma within the bracket.
        rows = np.array(path)
        j = int(np.searchsorted(rows[:, 3], target))
        s_lo, g_lo = rows[j - 1, 0], math.sqrt(rows[j - 1, 3]) - math.sqrt(target)
        s_hi, g_hi = rows[j, 0], math.sqrt(rows[j, 3]) - math.sqrt(target)
        side = 0
        while g_hi != 0.0 and g_lo != 0.0 and abs(s_hi - s_lo) > _EDGE_TOL:
            s_new = s_hi - g_hi * (s_hi - s_lo) / (g_hi - g_lo)
            g_new = math.sqrt(add_point(s_new)) - math.sqrt(target)
            if abs(g_new) < _DEPTH_TOL:
                s_lo = s_hi = s_new
                break
            if g_new < 0.0:
                s_lo, g_lo = s_new, g_new
                g_hi *= 0.5 if side == -1 else 1.0
                side = -1
            else:
                s_hi, g_hi = s_new, g_new
                g_lo *= 0.5 if side == 1 else 1.0
                side = 1
        sigma = s_hi if g_hi == 0.0 or abs(g_hi) <= abs(g_lo) else s_lo
        _, lam, p, _ = next(row for row in path if row[0] == sigma)
        shot = _shoot(np.array([lam]), edge(sigma, np.array([lam])), np.array([p]), curvature)
        solved[depth] = _state(depth, shot, p, radius, mu_t)
    return [solved[d] for d in depth_list]


def closed_sphere_pressure(radius: float, thickness: float, mu: float, stretch: float) -> float:
    """Pressure (Pa) of a closed spherical membrane inflated to ``stretch``, found by shooting.

    A check of the membrane equations used for the dome: shoots from the pole of a closed sphere of
    reference radius ``radius`` with pole stretch ``stretch`` and finds the pressure for which the meridian
    is symmetric about the equator (tangent vertical at ``S = pi R / 2``).  The exact answer is
    ``2 mu t / R (1/stretch - 1/stretch^7)``.

    Args:
        radius: reference radius (m).
        thickness: membrane thickness (m).
        mu: shear modulus (Pa).
        stretch: pole stretch (dimensionless, > 1).
    """
    _check_sizes(radius=radius, thickness=thickness, mu=mu)
    if not (math.isfinite(stretch) and stretch > 1.0):
        raise ValueError(f"stretch must be a finite number > 1, got {stretch!r}")

    def residual(x: np.ndarray) -> np.ndarray:
        n = x.shape[1]
        shot = _safe_shoot(np.full(n, stretch), np.zeros(n), x[0] * _sphere_pressure(stretch), 0.0)
        if shot is None:
            return np.full(x.shape, np.nan)
        return (shot.rim_angle - 0.5 * math.pi)[None, :]

    rel = _newton(residual, np.array([1.05]), np.ones(1))
    return float(rel[0] * _sphere_pressure(stretch)) * mu * thickness / radius
