"""One fit + intervals core: bounded, scaled least squares of named parameters against a residual.

Every fit of model parameters against measured residuals goes through here: calibrate's intervals,
diagnose's candidate fits, refits and polish, and the nuisance fit (issue 23, step 4). Plain data in,
arrays out; the caller's residual function holds whatever model it predicts with.

- `Parameters`: named values (SI units of each parameter) with bounds and a scale (the parameter table's
  `scale`, or a bound range): steps are solved in units of the scale, so parameters of different units
  weigh alike.
- `linear_step`: the bounded linear least-squares step of a residual on its Jacobian (optionally with a
  Gaussian prior on each parameter as extra rows).
- `gauss_newton`: damped Gauss-Newton (each linear step re-predicted nonlinearly, halved while it does not
  lower the cost, or, with a damping, Levenberg-Marquardt in Marquardt's scaling), returning a frozen `Fit`.
- `polish`: bounded derivative-free minimisation of a scalar cost (a signal that moves in whole samples,
  like a delay, has no useful derivative).
- `uncertainty`: the Gauss-Newton (linearised) covariance cov = s^2 (J_s^T J_s + P)^+ in scaled units, mapped
  to the parameters' units, where J_s is the Jacobian times the scales, P the prior's information
  (diag(scale / sigma)^2, none without a prior) and s^2 either 1 (a whitened residual: its variance is
  known) or the residual variance |r|^2 / (n - p); standard errors, correlations, the condition of J_s^T J_s
  and 95 % intervals (+- 1.96 sigma) follow from it.

Sign convention: a residual is data minus prediction and a Jacobian is the prediction's sensitivity to the
parameters (N, p; residual units per parameter unit), so a step solves residual ~ jac delta.
Rows of a Jacobian or residual with a non-finite entry (samples the model did not reach) are left out of
every solve.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.optimize import lsq_linear, minimize, minimize_scalar

Z95 = 1.96
"""Half-width of a two-sided 95 % normal interval, in standard deviations."""
AT_BOUND = 1e-6
"""A value within this fraction of its bound range of a bound is at the bound (the bounded solver's steps stay
strictly inside, so exact equality is rarely met)."""
DAMPING_GROWTH = 4.0
"""A damped (Levenberg-Marquardt) step that does not lower the cost is solved again with this many times the damping
(`GaussNewtonSettings.backtracks` times at most); each step that holds divides the damping by it. Measured on a
two-arm realistic plant's joint fit (seed 7, 26 pose parameters, a whitened residual whose response to a registration
micron is 22 noise units): from where the fit stalled (chi-square 37231), steps bounded to 1, 1/4 and 1/16 of each
prior sigma raised it to 256851, 275923 and 206477, while the damped steps with damping 0.3 and 1 lowered it to
35258 and 36178 (0.1 to 33887 with central-difference columns; docs/analysis.md, session 33)."""


def near_bound(values: np.ndarray, lower: np.ndarray, upper: np.ndarray, tolerance: float = AT_BOUND) -> np.ndarray:
    """(p,) bool: whether each value lies within `tolerance` times its bound range of a bound."""
    return np.minimum(values - lower, upper - values) <= tolerance * (upper - lower)


@dataclass(frozen=True)
class Parameters:
    """Named parameter values with their bounds and scales (1-D float arrays of one length, the
    parameters' own units). ValueError on mismatched lengths, non-finite entries, lower > upper, a
    non-positive scale or a value outside its bounds."""

    names: tuple[str, ...]
    values: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    scale: np.ndarray

    def __post_init__(self) -> None:
        arrays = {k: np.asarray(getattr(self, k), dtype=float) for k in ("values", "lower", "upper", "scale")}
        for key, array in arrays.items():
            if array.shape != (len(self.names),):
                raise ValueError(f"{key} has shape {array.shape}; expected ({len(self.names)},), one per name")
            if not np.isfinite(array).all():
                raise ValueError(f"{key} must be finite, got {array.tolist()}")
            object.__setattr__(self, key, array)
        if np.any(self.lower > self.upper) or np.any(self.scale <= 0):
            raise ValueError(f"need lower <= upper and scale > 0 for {list(self.names)}")
        if np.any(self.values < self.lower) or np.any(self.values > self.upper):
            raise ValueError(f"values {self.values.tolist()} of {list(self.names)} lie outside their bounds")

    def moved(self, delta: np.ndarray) -> Parameters:
        """The values moved by `delta` (parameter units) and clipped to the bounds."""
        moved = np.clip(self.values + delta, self.lower, self.upper)
        return Parameters(self.names, moved, self.lower, self.upper, self.scale)

    def with_values(self, values: np.ndarray) -> Parameters:
        """The same parameters at `values` (which must lie within the bounds)."""
        return Parameters(self.names, np.asarray(values, dtype=float), self.lower, self.upper, self.scale)

    def subset(self, index: list[int]) -> Parameters:
        """The parameters at positions `index`, in that order."""
        return Parameters(
            tuple(self.names[i] for i in index),
            self.values[index],
            self.lower[index],
            self.upper[index],
            self.scale[index],
        )

    def at_bound(self, tolerance: float = AT_BOUND) -> tuple[str, ...]:
        """Names whose value lies within `tolerance` times its bound range of a bound (`near_bound`)."""
        near = near_bound(self.values, self.lower, self.upper, tolerance)
        return tuple(n for n, flag in zip(self.names, near, strict=True) if flag)

    def as_dict(self) -> dict[str, float]:
        """{name: value}."""
        return {n: float(v) for n, v in zip(self.names, self.values, strict=True)}


@dataclass(frozen=True)
class Prior:
    """An independent Gaussian prior on each parameter: `mean` and 1-sigma `sigma` (parameter units)."""

    mean: np.ndarray
    sigma: np.ndarray

    def cost(self, values: np.ndarray) -> float:
        """sum(((values - mean) / sigma)^2): the prior's chi-square."""
        return float(np.sum(((np.asarray(values) - self.mean) / self.sigma) ** 2))


@dataclass(frozen=True)
class Uncertainty:
    """Linearised uncertainty of fitted parameters (see the module docstring).

    covariance: (p, p) in the parameters' units; std: (p,) 1-sigma; correlation: (p, p) (0 where a
    parameter has no variance); condition: largest over smallest eigenvalue of the scaled J^T J (prior left
    out; infinite where the data do not see a direction); variance: "unit" (whitened residual) or "residual"
    (s^2 = |r|^2 / (n - p))."""

    covariance: np.ndarray
    std: np.ndarray
    correlation: np.ndarray
    condition: float
    variance: str

    def intervals(self, values: np.ndarray) -> np.ndarray:
        """(p, 2) 95 % intervals about `values`: values -+ 1.96 std."""
        return np.column_stack([values - Z95 * self.std, values + Z95 * self.std])


def uncertainty(
    jac: np.ndarray, scale: np.ndarray, residual: np.ndarray | None = None, prior_sigma: np.ndarray | None = None
) -> Uncertainty:
    """The Gauss-Newton covariance of parameters with Jacobian `jac` (N, p; residual units per parameter
    unit) and scales `scale` (p,): with `residual` (N,) given, scaled by its variance |r|^2 / (n - p) (n - p at
    least 1); without, by 1 (a whitened residual). `prior_sigma` (p,) adds a Gaussian prior's information."""
    jac = np.asarray(jac, dtype=float)
    if jac.ndim != 2 or jac.shape[1] != len(scale):
        raise ValueError(f"the Jacobian has shape {jac.shape}; expected (N, {len(scale)})")
    rows = np.isfinite(jac).all(axis=1) & (np.isfinite(residual) if residual is not None else True)
    scaled = jac[rows] * scale
    information = scaled.T @ scaled
    eig = np.linalg.eigvalsh(information)
    if not len(eig):
        condition = float("nan")
    else:  # a direction the data do not see at all (eigenvalue 0, or round-off below it): infinite
        condition = float(eig[-1] / eig[0]) if eig[0] > eig[-1] * 1e-300 else float("inf")
    if prior_sigma is not None:
        information = information + np.diag((scale / prior_sigma) ** 2)
    variance = 1.0
    if residual is not None:
        r = np.asarray(residual, dtype=float)[rows]
        variance = float(r @ r) / max(len(r) - jac.shape[1], 1)
    cov_scaled = variance * np.linalg.pinv(information)
    sd_scaled = np.sqrt(np.clip(np.diag(cov_scaled), 0.0, None))
    denominator = np.outer(sd_scaled, sd_scaled)
    correlation = np.divide(cov_scaled, denominator, out=np.zeros_like(cov_scaled), where=denominator > 0)
    return Uncertainty(
        cov_scaled * np.outer(scale, scale),
        sd_scaled * scale,
        correlation,
        condition,
        "residual" if residual is not None else "unit",
    )


def linear_step(jac: np.ndarray, residual: np.ndarray, at: Parameters, prior: Prior | None = None) -> np.ndarray:
    """The step delta (p,; parameter units) minimising |residual - jac delta|^2 (plus the prior's chi-square
    at `at.values + delta`) with `at.values + delta` within the bounds, solved in scaled units; rows with a
    non-finite entry are left out. `jac` and `residual` may be a problem already `reduced`."""
    matrix, target = reduced(jac, residual)
    matrix = matrix * at.scale
    if prior is not None:
        matrix = np.vstack([matrix, np.diag(at.scale / prior.sigma)])
        target = np.concatenate([target, (prior.mean - at.values) / prior.sigma])
    bounds = ((at.lower - at.values) / at.scale, (at.upper - at.values) / at.scale)
    return lsq_linear(matrix, target, bounds=bounds).x * at.scale


def predictive_whitened(residual: np.ndarray, jac: np.ndarray, precision: np.ndarray) -> np.ndarray:
    """A held-out `residual` (n,) of unit-variance noise, predicted by a linear fit whose parameters carry the
    posterior `precision` (k, k: the inverse covariance in the units of jac's (n, k) columns), whitened by its
    predictive covariance I + jac precision^-1 jac^T (the noise plus what the fit leaves uncertain): for a right
    model and prior its sum of squares is a chi-square of n degrees. With jac precision^(-1/2) = Q S W^T (thin SVD),
    (I + Q S^2 Q^T)^(-1/2) = I + Q ((1 + S^2)^(-1/2) - 1) Q^T. Rows with a non-finite entry are left NaN."""
    out = np.full_like(residual, np.nan)
    rows = np.isfinite(residual) & np.isfinite(jac).all(axis=1)
    values, vectors = np.linalg.eigh(precision)
    spread = jac[rows] @ (vectors / np.sqrt(np.clip(values, 1e-300, None)))
    q, s, _ = np.linalg.svd(spread, full_matrices=False)
    r = residual[rows]
    out[rows] = r + q @ ((1.0 / np.sqrt(1.0 + s**2) - 1.0) * (q.T @ r))
    return out


def reduced(jac: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The least-squares problem |residual - jac x|^2 (jac (n, p)) over its rows without a non-finite entry, in
    at most p rows when it has many more: with the thin QR factorisation jac = Q R, |residual - jac x|^2 =
    |Q^T residual - R x|^2 + a constant, so every x (bounded or not) keeps its ranking and a whole residual's
    samples cost one factorisation, not an iterative solver's passes; stacked, the reductions of disjoint row
    sets are the reduction of their union (the held-out fits, `twin.analysis.heldout`)."""
    rows = np.isfinite(jac).all(axis=1) & np.isfinite(residual)
    matrix, target = jac[rows], residual[rows]
    if len(target) <= 2 * matrix.shape[1]:
        return matrix, target
    q, r = np.linalg.qr(matrix)
    return r, q.T @ target


@dataclass(frozen=True)
class Fit:
    """A fit's outcome: `parameters` at the optimum, its `residual` and `cost`, the last Jacobian a step
    used (None when no step was taken), the `uncertainty` from it (None likewise), the names at a bound and
    the number of residual evaluations."""

    parameters: Parameters
    residual: np.ndarray
    cost: float
    jacobian: np.ndarray | None
    uncertainty: Uncertainty | None
    at_bound: tuple[str, ...]
    evaluations: int

    @property
    def values(self) -> np.ndarray:
        """The fitted values (parameter units)."""
        return self.parameters.values


@dataclass(frozen=True)
class GaussNewtonSettings:
    """Damped Gauss-Newton controls: `iterations` linear steps at most, then up to `extra_iterations` more while
    each step lowers the cost by at least the fraction `extra_if_drop` (a fit still converging fast is not cut
    short; one that stalls is); a step that does not lower the cost is halved up to `backtracks` times (damped: solved
    again with `DAMPING_GROWTH` times the damping), then the fit stops; it also stops after a step that moves every
    parameter by less than `step_tolerance` of its scale;
    `whitened` says whether the residual's variance is 1 (the intervals' s^2); `extra_over_noise`: that drop is a
    fraction of the cost's excess over the noise's, one per finite entry of a whitened residual (a step from 1.05x
    the noise to 1.01x lowers the cost by 7 %, its excess by 80 %); `trust`, with a prior, bounds each step to that
    many of each parameter's prior sigmas (where the data barely see a direction, a full step along it is decided by
    the linearisation alone; None: unbounded); `damping`, the first step's Levenberg-Marquardt damping lambda (None:
    undamped steps, halved when they fail): each step minimises the linearised cost plus lambda sum_i c_i delta_i^2,
    c_i the curvature of parameter i's own term (its column's sum of squares plus its prior's 1 / sigma^2), so each
    parameter is held back by how strongly the data see it (Marquardt's scaling), not by its units or prior; a step
    that fails is solved again `DAMPING_GROWTH` times more damped, and each that holds eases the damping by as much;
    `settle_at_noise`: at the noise (`GaussNewtonHooks.at_noise`) the fit stops only once its last step lowered the
    cost by less than the number of parameters (a Gauss-Newton step lowers a quadratic cost by the squared distance
    to its minimum in posterior sigmas), not at once: a residual at the noise need not be at its minimum."""

    iterations: int = 4
    backtracks: int = 2
    step_tolerance: float = 0.0
    whitened: bool = True
    extra_iterations: int = 0
    extra_if_drop: float = 0.1
    extra_over_noise: bool = False
    trust: float | None = None
    damping: float | None = None
    settle_at_noise: bool = False


@dataclass(frozen=True)
class GaussNewtonHooks:
    """What a fit may be told besides its residual. `jacobian(parameters)` linearises again before each
    step (None: keep `start_jacobian` throughout); `at_noise(residual)` stops the fit before a new
    linearisation; `cost(residual, values)` defaults to the sum of squares of the finite residual (plus the
    prior's chi-square); `on_iteration(i, residual)` is told each iteration before its step; `promising(residual,
    predicted)` is asked before each step with the residual where the fit stands and the one the step's linearisation
    predicts (residual - J delta), and a step it refuses is not taken: the fit stops there (None: every step is
    taken; for steps that cost more than the fit can gain)."""

    jacobian: Callable[[Parameters], np.ndarray] | None = None
    at_noise: Callable[[np.ndarray], bool] | None = None
    cost: Callable[[np.ndarray, np.ndarray], float] | None = None
    on_iteration: Callable[[int, np.ndarray], None] | None = None
    promising: Callable[[np.ndarray, np.ndarray], bool] | None = None


def gauss_newton(
    residual: Callable[[Parameters], np.ndarray],
    start: Parameters,
    hooks: GaussNewtonHooks,
    settings: GaussNewtonSettings = GaussNewtonSettings(),
    prior: Prior | None = None,
    start_residual: np.ndarray | None = None,
    start_jacobian: np.ndarray | None = None,
) -> Fit:
    """Damped Gauss-Newton of `residual(parameters)` (N,) from `start` (see `GaussNewtonSettings` and
    `GaussNewtonHooks`). `start_residual` saves the first evaluation when known; `start_jacobian` is the
    first step's Jacobian (else `hooks.jacobian` gives it). ValueError with neither Jacobian."""
    if hooks.jacobian is None and start_jacobian is None:
        raise ValueError("gauss_newton needs a start_jacobian or a jacobian hook")
    evaluations = 0

    def cost(r: np.ndarray, values: np.ndarray) -> float:
        if hooks.cost is not None:
            return hooks.cost(r, values)
        return float(np.nansum(r**2)) + (prior.cost(values) if prior is not None else 0.0)

    def evaluated(parameters: Parameters) -> tuple[Parameters, np.ndarray, float]:
        nonlocal evaluations
        evaluations += 1
        r = residual(parameters)
        return parameters, r, cost(r, parameters.values)

    if start_residual is None:
        state = evaluated(start)
    else:
        state = (start, start_residual, cost(start_residual, start.values))
    jac, used, falling, damping = start_jacobian, None, True, settings.damping
    drop = float("inf")  # the last step's lowering of the cost
    for iteration in range(settings.iterations + settings.extra_iterations):
        if iteration >= settings.iterations and not falling:
            break
        if hooks.on_iteration is not None:
            hooks.on_iteration(iteration, state[1])
        if jac is None:
            settled = not settings.settle_at_noise or drop < len(start.values)
            if hooks.at_noise is not None and settled and hooks.at_noise(state[1]):
                break
            jac = hooks.jacobian(state[0])
        trusted = _trusted(state[0], prior, settings.trust)
        delta = _step(jac, state, trusted, prior, damping)
        if hooks.promising is not None and not hooks.promising(state[1], state[1] - jac @ delta):
            break
        trial = evaluated(state[0].moved(delta))
        for _ in range(settings.backtracks):
            if trial[2] < state[2]:
                break
            if damping is None:
                delta = delta / 2.0
            else:
                damping *= DAMPING_GROWTH
                delta = _step(jac, state, trusted, prior, damping)
            trial = evaluated(state[0].moved(delta))
        if not trial[2] < state[2]:
            break
        damping = None if damping is None else damping / DAMPING_GROWTH
        floor = float(np.isfinite(state[1]).sum()) if settings.extra_over_noise else 0.0
        drop = state[2] - trial[2]
        falling = drop >= settings.extra_if_drop * (state[2] - floor)
        state, used = trial, jac
        if np.all(np.abs(delta) < settings.step_tolerance * start.scale):
            break
        if hooks.jacobian is not None:
            jac = None
    parameters, r, c = state
    interval = None
    if used is not None:
        interval = uncertainty(
            used, start.scale, None if settings.whitened else r, prior.sigma if prior is not None else None
        )
    return Fit(parameters, r, c, used, interval, parameters.at_bound(), evaluations)


def _step(
    jac: np.ndarray,
    state: tuple[Parameters, np.ndarray, float],
    at: Parameters,
    prior: Prior | None,
    damping: float | None,
) -> np.ndarray:
    """The linear step from `state` (parameters, residual, cost) within `at`'s bounds: undamped without `damping` (or
    at 0); else with lambda c_i delta_i^2 added, c_i parameter i's curvature (its finite column's sum of squares
    plus the prior's 1 / sigma_i^2; a parameter neither sees is left free). The damping is a Gaussian about the
    current values of precision lambda c_i, folded with the prior into one (precisions add, means weigh by them), so
    the bounded solve stays one `linear_step`."""
    if not damping:
        return linear_step(jac, state[1], at, prior)
    rows = np.isfinite(jac).all(axis=1) & np.isfinite(state[1])
    information = np.zeros(len(at.values)) if prior is None else prior.sigma**-2.0
    curvature = np.sum(jac[rows] ** 2, axis=0) + information
    precision = information + damping * curvature
    mean = state[0].values if prior is None else prior.mean
    free = precision <= 0  # neither the data nor a prior see it: no damping row (a zero column's step is zero anyway)
    folded = (information * mean + damping * curvature * state[0].values) / np.where(free, 1.0, precision)
    sigma = 1.0 / np.sqrt(np.where(free, 1e-300, precision))
    return linear_step(jac, state[1], at, Prior(np.where(free, state[0].values, folded), sigma))


def _trusted(at: Parameters, prior: Prior | None, trust: float | None) -> Parameters:
    """`at` with its bounds narrowed to `trust` prior sigmas either side of its values (unchanged without both)."""
    if prior is None or trust is None:
        return at
    reach = trust * prior.sigma
    return replace(at, lower=np.maximum(at.lower, at.values - reach), upper=np.minimum(at.upper, at.values + reach))


def polish(cost: Callable[[np.ndarray], float], start: Parameters, reach: float = 5.0, evaluations: int = 60) -> Fit:
    """Bounded derivative-free minimisation of the scalar `cost(values)` from `start`: one parameter by a scan of
    `evaluations` points over `reach` scales either side of its start (and within its bounds), then Brent's
    bounded search between the best point's neighbours (a cost with several dips, such as a delay's against a
    sampled signal, is not left in the first dip Brent meets); several by Powell's method over the bounds with
    at most `evaluations` per parameter. The start is kept unless the result costs less. The Fit has no
    residual, Jacobian or uncertainty (a scalar cost gives none)."""
    calls = 0

    def counted(x: np.ndarray) -> float:
        nonlocal calls
        calls += 1
        return cost(x)

    x0 = start.values
    if len(x0) == 1:
        lo = max(start.lower[0], x0[0] - reach * start.scale[0])
        hi = min(start.upper[0], x0[0] + reach * start.scale[0])
        grid = np.linspace(lo, hi, evaluations)
        k = int(np.argmin([counted(np.array([v])) for v in grid]))
        bracket = (grid[max(k - 1, 0)], grid[min(k + 1, evaluations - 1)])
        best = minimize_scalar(lambda v: counted(np.array([v])), bounds=bracket, method="bounded")
        x = np.array([best.x])
    else:
        bounds = list(zip(start.lower, start.upper, strict=True))
        options = {"maxfev": evaluations * len(x0), "xtol": 1e-3}
        best = minimize(counted, x0, method="Powell", bounds=bounds, options=options)
        x = best.x
    at_start = counted(x0)
    fitted = start.with_values(np.clip(x, start.lower, start.upper)) if best.fun < at_start else start
    return Fit(fitted, np.empty(0), min(float(best.fun), at_start), None, None, fitted.at_bound(), calls)
