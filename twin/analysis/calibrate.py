"""Calibrate the skin like the paper: SLSQP over t_s, mu_NH, mu_fr, T_fl on one angled trajectory.

Cost (Narang et al., Eq. 1): J = w1 J_force + w2 J_thick with w1 = 1, w2 = 1e4.
- J_force = sum over the three axes of the RMS force error (N) over the trajectory's rows (the
  filtered, increment-end samples). Rows the model does not reach (fe non-convergence) count with a
  predicted force of zero, so failing early never lowers the cost.
- J_thick: the paper writes w2 (t_sim - 0.0151), which rewards a thinner sensor without bound. Here it is
  a proper penalty of the same weight and units, smooth for SLSQP: w2 sqrt((t_sim - 0.0151)^2 + eps^2)
  - w2 eps with eps = 0.1 mm (a pseudo-Huber absolute value: |dt| far from zero, quadratic within eps, so
  SLSQP sees a smooth valley it can follow while the other parameters move the inflated thickness).
Gradient: forward differences of J_force (the fe replays) and the chain rule for J_thick, its exact slope
at t_sim times the forward difference of t_sim (a smooth output of the inflation alone). A forward
difference of J_thick itself is its secant: at the valley's floor a step of 0.02 of T_fl's range moves
t_sim by 0.033 mm, a third of eps, and the secant slope is 2.7 per unit of scaled T_fl where the true one is
zero, twice the modulus's 1.2 (docs/analysis.md): SLSQP then spends its steps on T_fl and its line search
cuts every step short, the modulus barely moving.
The skin is inflated by the paper's thermal rule (fluid at T_fl), so the sensor thickness t_sim is an
output. Our BioTac cavity (facts/biotac.md geometry) holds far less fluid than the paper's FE fluid
domain: with beta_T = 0.01 /C, reaching 15.1 mm would need T_fl near 130 C. Calibration therefore uses
an effective beta_T, set once so that the starting T_fl inflates the starting skin to exactly 15.1 mm;
T_fl keeps its role (the inflation knob) and its bounds. Parameters are scaled to [0, 1] inside the
paper's bounds.

The optimiser stays SLSQP on this scalar cost (the paper's method; J_force is a sum of RMS errors, not a
sum of squares, so the least-squares core of `twin.analysis.fit` does not fit it).
Uncertainty: the force residual r (3 x rows, N) is linearised at the optimum by central differences;
cov = s^2 (J^T J)^-1 with s^2 = |r|^2 / (n - p) (`twin.analysis.fit.uncertainty`). Rows are low-pass
filtered, hence correlated, so these intervals are optimistic; they serve to flag parameters the
trajectory cannot identify (a warning when the scaled J^T J is ill-conditioned, two parameters correlate
beyond 0.95, or an interval spans more than the bounds).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import minimize

from fe.params import PAPER_CALIBRATION_BOUNDS, SkinParameters
from fe.sensor import SENSOR_THICKNESS
from twin.analysis.data import CampaignData, TrajectoryRecord
from twin.analysis.fit import Z95, uncertainty
from twin.analysis.predict import Predictor, TwinModel
from twin.effects import apply_skin

CALIBRATED = tuple(PAPER_CALIBRATION_BOUNDS)
"""SkinParameters fields the calibration moves: those with the paper's bounds (its t_s, mu_NH, mu_fr, T_fl)."""
FORCE_WEIGHT = 1.0
THICKNESS_WEIGHT = 1e4
THICKNESS_SMOOTHING = 0.1e-3
"""eps (m) of the pseudo-Huber thickness penalty."""
FIRST_STEP = 0.05
"""Largest move of SLSQP's first step, as a fraction of a parameter's bound range."""


@dataclass(frozen=True)
class CalibrationSettings:
    """SLSQP settings; `step` is the finite-difference step in scaled units (fraction of each bound range)."""

    max_iterations: int = 30
    tolerance: float = 1e-4
    """Stop when an iteration lowers the cost by less than this fraction of the starting cost."""
    step: float = 0.02
    bounds: dict[str, tuple[float, float]] = field(default_factory=lambda: dict(PAPER_CALIBRATION_BOUNDS))


@dataclass
class Calibration:
    """The optimum with its uncertainty (SI units; intervals are 95 %, +- 1.96 sigma)."""

    parameters: dict[str, float]
    start: dict[str, float]
    cost: float
    force_cost: float
    thickness_cost: float
    thickness: float  # m, sensor thickness after inflation at the optimum
    thermal_expansion: float  # 1/C, the effective beta_T used (see the module docstring)
    std: dict[str, float]
    intervals: dict[str, tuple[float, float]]
    correlation: list[list[float]]
    condition: float
    warnings: list[str]
    trajectories: list[tuple[int, int]]  # (sensor, trajectory id) used
    evaluations: int
    converged: bool
    message: str
    history: list[dict[str, float]] = field(default_factory=list)

    def model(self, base: TwinModel) -> TwinModel:
        """`base` with the calibrated skin (thermal inflation with the effective beta_T, as calibrated)."""
        skin = replace(base.skin, thermal_expansion=self.thermal_expansion, **self.parameters)
        return replace(base, skin=skin, inflation="thermal")

    def to_dict(self) -> dict:
        """JSON-ready form (the `twin calibrate --json` shape)."""
        out = dict(self.__dict__)
        out["intervals"] = {k: list(v) for k, v in self.intervals.items()}
        out["trajectories"] = [list(t) for t in self.trajectories]
        return out


def default_trajectories(datasets: list[CampaignData], indenter: str = "sphere_medium") -> list[TrajectoryRecord]:
    """The paper's choice: per sensor, the first angled trajectory of `indenter` (complete ones first)."""
    chosen = []
    for data in datasets:
        angled = [t for t in data.trajectories if t.indenter == indenter and not t.normal]
        angled.sort(key=lambda t: (not t.complete, t.trajectory_id))
        if angled:
            chosen.append(angled[0])
    if not chosen:
        raise ValueError(f"no angled {indenter} trajectory in the datasets; pick one with --trajectory")
    return chosen


def force_residual(predictor: Predictor, model: TwinModel, trajectories: list[TrajectoryRecord]) -> np.ndarray:
    """(rows, 3) predicted minus measured row force (N, biotac frame); unreached rows predict zero force. The
    replays of one model are solved as one batch (`Predictor.prefetch`)."""
    predictor.prefetch(model, trajectories)
    parts = []
    for t in trajectories:
        predicted = np.nan_to_num(predictor.predict(model, t).rows.force, nan=0.0)
        parts.append(predicted - t.rows["force"])
    return np.concatenate(parts)


def thickness_penalty(thickness: float) -> float:
    """w2 times the pseudo-Huber distance (m) of the sensor thickness from 15.1 mm (see module docstring)."""
    d = thickness - SENSOR_THICKNESS
    return THICKNESS_WEIGHT * (np.hypot(d, THICKNESS_SMOOTHING) - THICKNESS_SMOOTHING)


def thickness_penalty_slope(thickness: float) -> float:
    """d `thickness_penalty` / d thickness (1/m times the cost's units): w2 dt / sqrt(dt^2 + eps^2)."""
    d = thickness - SENSOR_THICKNESS
    return THICKNESS_WEIGHT * d / np.hypot(d, THICKNESS_SMOOTHING)


def calibrate(
    trajectories: list[TrajectoryRecord],
    base: TwinModel,
    predictor: Predictor | None = None,
    settings: CalibrationSettings = CalibrationSettings(),
    progress: Callable[[int, float], None] | None = None,
) -> Calibration:
    """Minimise the paper's cost over the calibrated parameters from `base.skin` (see module docstring).

    progress(evaluation, cost) is called after every cost evaluation.
    """
    if not trajectories:
        raise ValueError("calibration needs at least one trajectory")
    predictor = predictor or Predictor()
    low = np.array([settings.bounds[n][0] for n in CALIBRATED])
    high = np.array([settings.bounds[n][1] for n in CALIBRATED])
    start = np.array([getattr(base.skin, n) for n in CALIBRATED])
    if np.any(start < low) or np.any(start > high):
        raise ValueError(f"the starting skin {dict(zip(CALIBRATED, start, strict=True))} is outside the bounds")
    history: list[dict[str, float]] = []
    expansion = effective_thermal_expansion(predictor, base)

    def model_at(z: np.ndarray) -> TwinModel:
        values = low + np.clip(z, 0.0, 1.0) * (high - low)
        calibrated = dict(zip(CALIBRATED, (float(v) for v in values), strict=True))
        skin = replace(base.skin, thermal_expansion=expansion, **calibrated)
        return replace(base, skin=skin, inflation="thermal")

    def terms(z: np.ndarray) -> tuple[float, float, float]:
        model = model_at(z)
        try:
            skin = apply_skin(model.skin, model.effects)
            thickness = predictor.inflated(skin, model.mesh_max_edge, "thermal")[1].thickness
            residual = force_residual(predictor, model, trajectories)
        except (RuntimeError, ValueError):
            return np.inf, np.inf, np.nan
        force_cost = FORCE_WEIGHT * float(np.sum(np.sqrt(np.mean(residual**2, axis=0))))
        return force_cost, float(thickness_penalty(thickness)), thickness

    def evaluated(z: np.ndarray) -> tuple[float, float, float]:
        """`terms(z)`, recorded in the history (and reported) as one cost evaluation."""
        force_cost, thick_cost, thickness = terms(z)
        total = force_cost + thick_cost
        history.append({**_calibrated_values(model_at(z).skin), "cost": total, "sensor_thickness": thickness})
        if progress is not None:
            progress(len(history), total)
        return force_cost, thick_cost, thickness

    def cost(z: np.ndarray) -> float:
        return _bounded(sum(evaluated(z)[:2]))

    z0 = (start - low) / (high - low)

    def gradient(z: np.ndarray) -> np.ndarray:
        """Forward differences of `settings.step` in scaled units (backward at the upper bound) of the force
        term, plus the thickness penalty's exact slope times the difference of the thickness (see the module
        docstring); the predictor caches every model, so SLSQP's repeated points cost nothing."""
        at = evaluated(z)
        slope, out = thickness_penalty_slope(at[2]), np.zeros_like(z)
        for i in range(len(z)):
            h = settings.step if z[i] + settings.step <= 1.0 else -settings.step
            shifted = z.copy()
            shifted[i] += h
            near = evaluated(shifted)
            if np.isfinite(at[0]) and np.isfinite(near[0]):
                out[i] = (near[0] - at[0]) / h + slope * (near[2] - at[2]) / h
            else:  # the model fails on one side: the failure's cost (1e6) as in `cost`
                out[i] = (_bounded(sum(near[:2])) - _bounded(sum(at[:2]))) / h
        return out

    # SLSQP's first step is minus the gradient (unit Hessian) and its tolerance is absolute: divide the
    # cost so that the first step moves no parameter by more than FIRST_STEP of its range.
    f_start = cost(z0)
    if not np.isfinite(f_start) or f_start >= 1e6:
        raise RuntimeError("the model fails at the starting parameters; pass a --model that runs")
    divisor = max(float(np.max(np.abs(gradient(z0)))) / FIRST_STEP, f_start, 1e-12)
    result = minimize(
        lambda z: cost(z) / divisor,
        z0,
        jac=lambda z: gradient(z) / divisor,
        method="SLSQP",
        bounds=[(0.0, 1.0)] * len(CALIBRATED),
        options={"maxiter": settings.max_iterations, "ftol": settings.tolerance * f_start / divisor},
    )
    best = model_at(result.x)
    force_cost, thick_cost, thickness = terms(result.x)
    jac = _residual_jacobian(predictor, model_at, result.x, trajectories, settings.step)
    residual = force_residual(predictor, best, trajectories).ravel()
    std, corr, condition = _uncertainty(jac, residual, high - low)
    parameters = _calibrated_values(best.skin)
    intervals = {n: (parameters[n] - Z95 * std[n], parameters[n] + Z95 * std[n]) for n in CALIBRATED}
    return Calibration(
        parameters=parameters,
        start=dict(zip(CALIBRATED, (float(v) for v in start), strict=True)),
        cost=force_cost + thick_cost,
        force_cost=force_cost,
        thickness_cost=thick_cost,
        thickness=thickness,
        thermal_expansion=expansion,
        std=std,
        intervals=intervals,
        correlation=corr.round(4).tolist(),
        condition=condition,
        warnings=_warnings(std, corr, condition, low, high),
        trajectories=[(t.sensor_id, t.trajectory_id) for t in trajectories],
        evaluations=len(history),
        converged=bool(result.success),
        message=str(result.message),
        history=history,
    )


def effective_thermal_expansion(predictor: Predictor, base: TwinModel) -> float:
    """beta_T (1/C) such that the thermal rule at `base.skin.fluid_temperature` adds the fluid volume that
    inflates `base`'s skin to 15.1 mm (see the module docstring)."""
    skin = apply_skin(base.skin, base.effects)
    fe, inflation = predictor.inflated(skin, base.mesh_max_edge, "thickness")
    warming = skin.fluid_temperature - skin.reference_temperature
    if warming <= 0:
        raise ValueError(
            f"T_fl ({skin.fluid_temperature} C) must exceed the reference ({skin.reference_temperature} C)"
        )
    added = inflation.volume_change / skin.inflation_volume_scale
    return float(added / (fe.geometry.cavity_volume_reference * warming))


def _bounded(total: float) -> float:
    """A cost SLSQP can use: a failed model's (non-finite) cost counts as 1e6."""
    return total if np.isfinite(total) else 1e6


def _calibrated_values(skin: SkinParameters) -> dict[str, float]:
    return {n: float(getattr(skin, n)) for n in CALIBRATED}


def _residual_jacobian(
    predictor: Predictor,
    model_at: Callable[[np.ndarray], TwinModel],
    z: np.ndarray,
    trajectories: list[TrajectoryRecord],
    step: float,
) -> np.ndarray:
    """(3 rows, p) central-difference Jacobian of the force residual in scaled parameters (one-sided at a
    bound)."""
    columns = []
    for i in range(len(z)):
        up, down = z.copy(), z.copy()
        up[i] = min(z[i] + step, 1.0)
        down[i] = max(z[i] - step, 0.0)
        r_up = force_residual(predictor, model_at(up), trajectories).ravel()
        r_down = force_residual(predictor, model_at(down), trajectories).ravel()
        columns.append((r_up - r_down) / (up[i] - down[i]))
    return np.column_stack(columns)


def _uncertainty(jac: np.ndarray, residual: np.ndarray, ranges: np.ndarray) -> tuple[dict, np.ndarray, float]:
    """Per-parameter standard deviation (SI), correlation matrix and condition of the scaled J^T J, from the
    (rows, p) Jacobian in scaled units (`twin.analysis.fit.uncertainty`, s^2 the residual variance)."""
    spread = uncertainty(jac / ranges, ranges, residual)
    std = {n: float(s) for n, s in zip(CALIBRATED, spread.std, strict=True)}
    return std, spread.correlation, spread.condition


def _warnings(std: dict, corr: np.ndarray, condition: float, low: np.ndarray, high: np.ndarray) -> list[str]:
    out = []
    if condition > 1e6:
        out.append(f"J^T J is ill-conditioned ({condition:.1e}): some parameter combination is not identified")
    for i, a in enumerate(CALIBRATED):
        if 2 * Z95 * std[a] > high[i] - low[i]:
            out.append(f"{a} is not identifiable: its 95 % interval is wider than its bounds")
        for j in range(i + 1, len(CALIBRATED)):
            if abs(corr[i, j]) > 0.95:
                out.append(f"{a} and {CALIBRATED[j]} are correlated ({corr[i, j]:+.2f}): only a combination is fitted")
    return out
