"""Nuisances first: the standard unknowns of every real campaign, fitted before a missing effect is sought.

A real testbed never matches the nominal model exactly even when nothing is missing from it: each arm's
registration leaves the indenter path off by a fraction of a millimetre to a millimetre and a half
(paper: 0.5-1.5 mm), and each BioTac's skin has its own thickness, modulus and friction (unit-to-unit
spread; the paper calibrates t_s, mu_NH and mu_fr per sensor). These are fitted here, as the paper
calibrates them, and diagnosis then ranks candidate effects on what remains:

- `registration_offset` (dx, dy, dz; m, biotac frame) per (sensor, arm): the arms are registered apart;
- `registration_rotation` (rx, ry, rz; rad, biotac frame, about its origin) per (sensor, arm): the rest of the
  registration's rigid error;
- `joint_offset` (q1..q7; rad) per (sensor, arm): the arm's joint zero offsets against its kinematic model. They
  move the tool by an amount that depends on the arm's pose, so presses of one arm in different poses (a
  normal and a 30-degree press at one point) are off by different amounts, which one offset per arm cannot
  take (measured: 0.29 mm apart on the realistic plant of tests/test_nuisances.py). The registration rotation and
  the joint offsets act through each trajectory's pose error (`twin.analysis.pose_error`, exact kinematics at its
  joint readings): the tip where the commanded depth is zero moves (on top of the registration offset), the press
  turns and stretches (`TwinModel.path_slope`) and the indenter tilts (`TwinModel.indenter_tilt`); at the plant's
  own values they leave a realistic null's 31 presses at the noise (0.998x; 1.53x with the tips moved but the
  indenter neither tilted nor the press turned, docs/analysis.md). Their sensitivities cost six replay sets (the
  pose errors' three tilts and three slopes, every trajectory at once): a trajectory's prediction depends on its
  own pose only, so its rows of the registration offset's and the pose errors' columns, times the pose error's
  derivatives (`pose_jacobian`), are theirs (chain rule). Row-only files have no joint readings and get the
  registration offset alone;
- `skin_thickness`, `skin_modulus`, `indenter_friction` (scale factors) per sensor.

The F/T bias is removed by taring and each trajectory's channel offsets are projected out of the
residual (`twin.analysis.residual`), as is each sensor's PDC gain: those nuisances need no fit. The
mount's pose is what registration measures (its holes); what registration gets wrong of it is the
per-arm offset.

The fit is Levenberg-Marquardt on the whitened residual (`DAMPING`) with a Gaussian prior on each nuisance about the
model's own value (`PRIORS`, wide: about twice the spread a real campaign shows) and each step within a prior sigma
(`TRUST`), finite-difference sensitivities of microns (`STEPS`; a registration column replays only that arm's
trajectories), started from each arm's best registration start (its contact-onset estimate, `REGISTRATION_STARTS` or
the model's values) because a large offset is nonlinear, and, when the result is not yet at the noise, the
registration starts tried again about the fit. A fit is judged on the samples its residual's replays reached; when
its values reach more (a nominal model pressing deeper than the plant may stop where its fe does not converge), it
is taken again on the residual at those values, so no sample the fitted model predicts is left out of the fit.
Whether the nuisances explain the data is judged held out: each trajectory is predicted by the nuisances fitted
(linearised at the fit) without it, and that prediction is whitened by its predictive spread, the noise plus what
the other trajectories and the priors leave of the nuisances uncertain (at 0.01 N of noise against Newtons of force,
no campaign fixes an arm's pose well enough for the raw prediction to be noise; a press that the others predict
worse than their uncertainty allows still fails). Which candidate effects the campaign cannot tell apart from the
nuisances is the fraction of each effect's signature that lies in the span of the nuisances' signatures
(`confounded`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from twin.analysis.data import CampaignData, TrajectoryRecord
from twin.analysis.fit import (
    Fit,
    GaussNewtonHooks,
    GaussNewtonSettings,
    Parameters,
    Prior,
    gauss_newton,
    linear_step,
    predictive_whitened,
    reduced,
)
from twin.analysis.fit import uncertainty as fit_uncertainty
from twin.analysis.onset import onset_estimate
from twin.analysis.pose_error import ArmPath, arm_path, pose_error, pose_jacobian
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.residual import Base, ModelFor, base_residual, model_requests
from twin.backend import N_JOINTS
from twin.effects import EFFECTS, REGISTRATION, EffectParameter, registration_values, registration_vector
from twin.registration import PAPER_JOINT_OFFSET_STD

SKIN_NUISANCES = ("skin_thickness", "skin_modulus", "indenter_friction")
"""Per-sensor skin nuisances (each a scale factor on a skin parameter)."""
NUISANCE_EFFECTS = (*SKIN_NUISANCES, REGISTRATION)
"""Library effects the nuisance stage fits; diagnosis does not offer them as missing effects."""
JOINT_OFFSET = "joint_offset"
"""The nuisance of an arm's joint zero offsets (not a library effect: it acts through the pose error)."""
JOINT_PARAMETERS = tuple(EffectParameter(f"q{j + 1}", 0.0, -0.01, 0.01, 1e-3, "rad") for j in range(N_JOINTS))
"""The joint offsets' parameters, chain order (bounds: 5x the prior)."""
REGISTRATION_ROTATION = "registration_rotation"
"""The nuisance of an arm's registration rotation (not a library effect: it acts through the pose error)."""
ROTATION_PARAMETERS = tuple(EffectParameter(f"r{axis}", 0.0, -0.04, 0.04, 1e-3, "rad") for axis in "xyz")
"""The registration rotation's parameters: a rotation vector (rad, biotac frame, about its origin; bounds 4x the
prior)."""
DERIVED = (REGISTRATION_ROTATION, JOINT_OFFSET)
"""Nuisances whose sensitivities come by the chain rule from the pose error's (`_derived_columns`), not replays."""
POSE_STEPS = {"indenter_tilt": 5e-4, "path_slope": 2e-3}
"""Finite-difference step of each pose error (`TwinModel`; rad, and m per m of depth: 6 um at 3 mm)."""
STEPS = {REGISTRATION: 2e-5, "skin_thickness": 0.01, "skin_modulus": 0.01, "indenter_friction": 0.05}
"""Finite-difference step of each fitted nuisance (m, scale factors): a press's force is far from linear over the
library's steps (a 0.2 mm registration step: the chain rule's columns 7-68 % off direct ones on the paper-depth
presses of tests/test_nuisances.py; 1-16 % at 20 um), and the fit must place the indenter to microns."""
PRIORS = {
    "skin_thickness": 0.1,
    "skin_modulus": 0.1,
    "indenter_friction": 0.3,
    REGISTRATION: 1.5e-3,
    REGISTRATION_ROTATION: 1e-2,
    JOINT_OFFSET: PAPER_JOINT_OFFSET_STD,
}
"""1-sigma prior of each nuisance about the model's value (scale factors: relative; registration: m per
axis; registration rotation: rad per axis; joint offsets: rad per joint), about twice a real campaign's spread
(5 % skin, 10 % friction, registration 0.5-1.5 mm, a mount placed to 2 mrad); the joint offsets' is the RMS that
reproduces the paper's registration band (`twin.registration.PAPER_JOINT_OFFSET_STD`)."""
REGISTRATION_STARTS = tuple(
    np.array(v) for v in ((1e-3, 0, 0), (-1e-3, 0, 0), (0, 1e-3, 0), (0, -1e-3, 0), (0, 0, 1e-3), (0, 0, -1e-3))
)
"""Registration offsets (m) also tried, per arm, before the first step and about a fit not at the noise."""
ITERATIONS = 4
"""Gauss-Newton iterations of one fit (each a finite-difference sensitivity: one replay set per parameter)."""
EXTRA_ITERATIONS = 8
"""Iterations past `ITERATIONS` while each step still lowers the cost's excess over the noise by a tenth (measured on
a realistic null of 31 presses: four steps took 48.8x the noise to 3.3x, the last still a third lower)."""
TRUST = 1.0
"""Prior sigmas a Gauss-Newton step may move each nuisance (`GaussNewtonSettings.trust`): two presses leave most of
an arm's 13 pose parameters to the prior, and full steps along those directions took the paper-depth presses of
tests/test_nuisances.py to a registration 3 mm off and a joint 5 sigmas off (6.3x the noise)."""
DAMPING = 1e-2
"""The first step's Levenberg-Marquardt damping (`GaussNewtonSettings.damping`; it adapts: multiplied by
`twin.analysis.fit.DAMPING_GROWTH` while a step fails, divided by it after one that holds). A registration micron
moves a whitened residual by tens of noise units, and the pose's response bends within a few microns (forward and
central differences 12-64 % apart on a cylinder's angled press), so a step of a fixed share of the priors fails where
one damped by what the data see holds (measured on seed 7's realistic joint fit, `DAMPING_GROWTH`)."""
BACKTRACKS = 6
"""Times a step that does not lower the cost is solved again, more damped (up to 4^6 times the damping; a replay set
each, about a twelfth of a sensitivity's on a two-arm campaign)."""
REFITS_ON_REACHED = 2
"""Times the fit is taken again, from its values and on the residual they reach, when those values reach samples
the residual it was fitted on did not (a replay that stopped early, e.g. a nominal model pressing too deep for its
fe to converge, leaves the rest of its trajectory out of that fit's chi-square)."""
REACHED_MORE = 1e-3
"""Fraction of the data's samples the fitted values must reach besides those fitted on to be fitted again (the 46-press
GPU fit refitted for one sample more: a sensitivity wave and steps for nothing, docs/scale.md session 30)."""
USABLE_ROWS = 0.9
"""A sensitivity column whose replay reached fewer than this fraction of the samples is not used."""
STANDOFF_LOADED = 5.0
"""A trajectory starts in contact when its model's force at the standoff pose (where the recording is tared) exceeds
this many times the largest force channel's noise (sigma, N): its tare is loaded, and on a real testbed the arm's
move there, not in the data, set the skin's friction state (`Predictor.standoff_force`)."""
CONFOUNDED_FRACTION = 0.9
"""An effect whose signature lies this much (fraction of its squared norm) in the span of the nuisances'
signatures cannot be told apart from them on this campaign."""


@dataclass(frozen=True)
class Slot:
    """One fitted nuisance parameter: an effect's parameter for one sensor (skin) or one (sensor, arm), or, for an
    effect fitted jointly with the nuisances, for every trajectory (sensor None)."""

    effect: str
    parameter: str
    sensor: int | None  # None: every sensor (an effect fitted jointly)
    arm: str | None  # None: every arm of the sensor (skin nuisances)

    @property
    def label(self) -> str:
        """`sensor 2 left registration_offset.dx` style name (`time_delay.seconds` for an effect fitted jointly)."""
        if self.sensor is None:
            return f"{self.effect}.{self.parameter}"
        where = f"sensor {self.sensor}" + (f" {self.arm}" if self.arm else "")
        return f"{where} {self.effect}.{self.parameter}"

    def applies(self, trajectory: TrajectoryRecord) -> bool:
        """Whether this parameter acts on `trajectory`."""
        return self.sensor in (None, trajectory.sensor_id) and self.arm in (None, trajectory.arm)


@dataclass(frozen=True)
class NuisanceValues:
    """Values of the nuisance slots; `model_for` is the model of one trajectory (a `ModelFor`); `paths` holds
    the trajectories' `ArmPath`s by (sensor, trajectory id) (worked out when first asked for)."""

    slots: tuple[Slot, ...]
    values: tuple[float, ...]
    paths: dict[tuple[int, int], ArmPath] = field(default_factory=dict, compare=False)

    def model_for(self, model: TwinModel, trajectory: TrajectoryRecord) -> TwinModel:
        """`model` with the nuisances of `trajectory`'s sensor and arm merged into its effects; its registration
        rotation and joint offsets move its path on top of its arm's registration offset, turn the press and tilt
        the indenter (`twin.analysis.pose_error`)."""
        effects: dict[str, dict[str, float]] = {}
        for slot, value in zip(self.slots, self.values, strict=True):
            if slot.applies(trajectory) and slot.effect not in DERIVED:
                effects.setdefault(slot.effect, {})[slot.parameter] = value
        rotation, joints = self.arm_pose(trajectory)
        if not (joints.any() or rotation.any()):
            return model.with_effects(effects)
        error = pose_error(self.path(trajectory), rotation, joints)
        given = {**model.effects.get(REGISTRATION, {}), **effects.get(REGISTRATION, {})}
        effects[REGISTRATION] = registration_values(registration_vector(given) + error.offset)
        return replace(
            model.with_effects(effects),
            indenter_tilt=tuple(float(v) for v in np.add(model.indenter_tilt, error.tilt)),
            path_slope=tuple(float(v) for v in np.add(model.path_slope, error.slope)),
        )

    def arm_pose(self, trajectory: TrajectoryRecord) -> tuple[np.ndarray, np.ndarray]:
        """(registration rotation (3,) rad, joint offsets (7,) rad) of `trajectory`'s sensor and arm (zero where
        not fitted)."""
        rotation, joints = np.zeros(3), np.zeros(N_JOINTS)
        for slot, value in zip(self.slots, self.values, strict=True):
            if slot.effect in DERIVED and slot.applies(trajectory):
                (joints if slot.effect == JOINT_OFFSET else rotation)[_index(slot)] = value
        return rotation, joints

    def path(self, trajectory: TrajectoryRecord) -> ArmPath:
        """`trajectory`'s `ArmPath` (kept in `paths`)."""
        key = (trajectory.sensor_id, trajectory.trajectory_id)
        if key not in self.paths:
            self.paths[key] = arm_path(trajectory)
        return self.paths[key]

    @property
    def parameters(self) -> Parameters:
        """The values as `twin.analysis.fit` parameters (named by slot label, with their bounds and scales)."""
        ps = [_parameter(s) for s in self.slots]
        return Parameters(
            tuple(s.label for s in self.slots),
            np.array(self.values),
            np.array([p.lower for p in ps]),
            np.array([p.upper for p in ps]),
            np.array([p.scale for p in ps]),
        )

    def at(self, parameters: Parameters) -> NuisanceValues:
        """These slots at `parameters`' values."""
        return replace(self, values=tuple(float(v) for v in parameters.values))

    def moved(self, delta: np.ndarray) -> NuisanceValues:
        """Values moved by `delta` and clipped to each parameter's bounds."""
        return self.at(self.parameters.moved(delta))

    def as_dict(self) -> dict[str, float]:
        """{slot label: value} (SI units, scale factors dimensionless)."""
        return {s.label: v for s, v in zip(self.slots, self.values, strict=True)}


def _parameter(slot: Slot) -> EffectParameter:
    derived = {JOINT_OFFSET: JOINT_PARAMETERS, REGISTRATION_ROTATION: ROTATION_PARAMETERS}
    parameters = derived[slot.effect] if slot.effect in derived else EFFECTS[slot.effect].parameters
    return next(p for p in parameters if p.name == slot.parameter)


def _index(slot: Slot) -> int:
    """The chain index of a joint-offset slot, the axis of a registration rotation's."""
    return int(slot.parameter[1:]) - 1 if slot.effect == JOINT_OFFSET else "xyz".index(slot.parameter[1])


def _prior(values: NuisanceValues) -> Prior:
    """The Gaussian prior about `values`: 1 sigma in each parameter's units (a relative prior times the off
    value for scale factors; an effect fitted jointly: its range)."""
    parameters = [_parameter(s) for s in values.slots]
    sigma = [  # an effect fitted jointly: as wide as its range
        PRIORS[s.effect] * (p.off or 1.0) if s.effect in PRIORS else p.upper - p.lower
        for s, p in zip(values.slots, parameters, strict=True)
    ]
    return Prior(np.array(values.values), np.array(sigma))


def model_values(slots: tuple[Slot, ...], model: TwinModel) -> NuisanceValues:
    """The model's own value of each slot (the off value where the model lacks the effect)."""
    return NuisanceValues(
        slots,
        tuple(
            _parameter(s).off
            if s.effect in DERIVED
            else EFFECTS[s.effect].values(model.effects.get(s.effect))[s.parameter]
            for s in slots
        ),
    )


def nuisance_slots(trajectories: list[TrajectoryRecord], jointly: tuple[str, ...] = ()) -> tuple[Slot, ...]:
    """The slots a campaign has: skin scales per sensor, registration offsets per (sensor, arm) used, and that
    arm's registration rotation and joint offsets where every one of its trajectories has joint readings (not a
    row-only file); then the parameters of the library effects `jointly` fitted with them (every trajectory's)."""
    slots = []
    for sensor in sorted({t.sensor_id for t in trajectories}):
        for effect in SKIN_NUISANCES:
            slots += [Slot(effect, p.name, sensor, None) for p in EFFECTS[effect].parameters]
        for arm in sorted({t.arm for t in trajectories if t.sensor_id == sensor}):
            slots += [Slot(REGISTRATION, p.name, sensor, arm) for p in EFFECTS[REGISTRATION].parameters]
            if not any(t.rows_only for t in trajectories if (t.sensor_id, t.arm) == (sensor, arm)):
                slots += [Slot(REGISTRATION_ROTATION, p.name, sensor, arm) for p in ROTATION_PARAMETERS]
                slots += [Slot(JOINT_OFFSET, p.name, sensor, arm) for p in JOINT_PARAMETERS]
    slots += [Slot(effect, p.name, None, None) for effect in jointly for p in EFFECTS[effect].parameters]
    return tuple(slots)


@dataclass
class NuisanceFit:
    """The fitted nuisances, the residual at them and how well they explain the data (whitened RMS, 1 =
    noise)."""

    values: NuisanceValues
    base: Base  # the residual at the fitted nuisances (its model_for applies them)
    jacobian: np.ndarray  # (N, k) profiled whitened sensitivity at the fit, columns in slot order
    rms_before: float  # the model without nuisances fitted
    rms_after: float
    heldout_rms: float  # each trajectory predicted by the nuisances fitted without it
    heldout_is_noise: bool  # those predictions, whitened by their predictive spread, pass the noise test
    is_noise: bool  # the in-sample residual passes the noise test (fitted parameters counted)
    correlation: list[list[float]]
    at_bound: list[str]
    confounded: dict[str, float] = field(default_factory=dict)  # effect -> fraction in the nuisance span
    heldout_by_trajectory: list[dict] = field(default_factory=list)  # `by_trajectory`: where the held-out test fails
    heldout_predictive_rms: float | None = None  # the held-out predictions whitened by their predictive spread

    def project(self, columns: np.ndarray) -> np.ndarray:
        """Columns (N, k) (or a vector) with their least-squares component on the nuisance signatures
        removed in the chi-square's metric (its squares plus the PDC gains' prior cost, `GainNuisance.penalty_rows`;
        rows with a NaN anywhere are left NaN): what a joint refit with the nuisances leaves."""
        matrix = np.asarray(columns, dtype=float)
        flat = matrix.reshape(len(matrix), -1)
        rows = np.isfinite(flat).all(axis=1) & np.isfinite(self.jacobian).all(axis=1)
        out = np.full_like(flat, np.nan)
        jac, target = np.where(rows[:, None], self.jacobian, 0.0), np.where(rows[:, None], flat, 0.0)
        penalty = self.base.nuisance.penalty_rows
        system = np.vstack([jac[rows], penalty(jac)]), np.vstack([target[rows], penalty(target)])
        coefficients = np.linalg.lstsq(*system, rcond=1e-10)[0]
        out[rows] = flat[rows] - self.jacobian[rows] @ coefficients
        return out.reshape(matrix.shape)

    def confounding(self, effect: str, jac: np.ndarray) -> float:
        """The largest fraction of the squared norm of one of `effect`'s signature columns that lies in
        the nuisances' span; recorded in `confounded`."""
        rows = np.isfinite(jac).all(axis=1) & np.isfinite(self.jacobian).all(axis=1)
        left = self.project(np.where(rows[:, None], jac, np.nan))[rows]
        total = np.sum(jac[rows] ** 2, axis=0)
        fraction = float(np.max(1.0 - np.sum(left**2, axis=0) / np.maximum(total, 1e-300)))
        self.confounded[effect] = fraction
        return fraction

    def cannot_tell_apart(self) -> list[str]:
        """Effects whose signature lies at least `CONFOUNDED_FRACTION` in the nuisances' span."""
        return sorted(k for k, v in self.confounded.items() if v >= CONFOUNDED_FRACTION)

    def to_dict(self) -> dict:
        """JSON-ready summary (the `nuisances` block of `twin diagnose --json`)."""
        return {
            "values": self.values.as_dict(),
            "rms_before": self.rms_before,
            "rms_after": self.rms_after,
            "heldout_rms": self.heldout_rms,
            "heldout_predictive_rms": self.heldout_predictive_rms,
            "heldout_is_noise": self.heldout_is_noise,
            "is_noise": self.is_noise,
            "correlation": self.correlation,
            "at_bound": self.at_bound,
            "confounded": dict(self.confounded),
            "cannot_tell_apart": self.cannot_tell_apart(),
            "heldout_by_trajectory": self.heldout_by_trajectory,
        }


def fit_nuisances(
    datasets: list[CampaignData],
    model: TwinModel,
    predictor: Predictor,
    report: Callable[[str], None] = lambda _: None,
    jointly: tuple[str, ...] = (),
) -> NuisanceFit:
    """Fit the nuisances of `datasets` about `model` (see the module docstring), and with them the library effects
    `jointly` (from `model`'s values of them, with priors as wide as their ranges): a missing effect found about
    nuisances that were fitted without it, refitted with them."""
    nominal = base_residual(datasets, model, predictor)
    slots = nuisance_slots(nominal.trajectories, jointly)
    prior = model_values(slots, model)
    report("registration starts")  # each arm from its contact onsets first: most of a realistic misfit is registration
    fitted_on, start = nominal, _best_starts(nominal, model, predictor, prior, nominal.residual.values)
    for refits in range(REFITS_ON_REACHED + 1):
        fitted = _gauss_newton(fitted_on, model, predictor, start, prior, report, settle=refits > 0)
        if not (np.isfinite(fitted.cost) and fitted_on.noise_test(fitted.residual, len(slots)).is_noise):
            report("registration starts")  # each arm its best start about the fit, and the fit of lower cost kept
            starts = _best_starts(fitted_on, model, predictor, prior.at(fitted.parameters), fitted.residual)
            again = _gauss_newton(fitted_on, model, predictor, starts, prior, report, settle=refits > 0)
            fitted = min(fitted, again, key=lambda f: f.cost)
        values = prior.at(fitted.parameters)
        base = base_residual(datasets, model, predictor, values.model_for, len(slots), nominal.sigma)
        if base.reached - fitted_on.reached <= REACHED_MORE * base.samples or refits == REFITS_ON_REACHED:
            break
        report(f"fitted again on the {base.reached - fitted_on.reached} samples its values reach besides")
        fitted_on, start = base, values
    same_samples = all(np.array_equal(a, b) for a, b in zip(base.masks, fitted_on.masks, strict=True))
    jac = fitted.jacobian
    if jac is None or not same_samples:
        jac = _jacobian(base, model, predictor, values)
    heldout, predictive = _leave_one_trajectory_out(base, jac, values, prior)
    return NuisanceFit(
        values,
        base,
        jac,
        _profiled_rms(nominal, nominal.residual.values),
        _profiled_rms(base, base.residual.values),
        _rms(heldout),
        base.noise_test(predictive, 0).is_noise,
        base.noise_test(base.residual.values).is_noise,
        _correlation(jac, values),
        list(fitted.at_bound),
        heldout_by_trajectory=by_trajectory(base, heldout, predictive, standoff_forces(base, model, predictor)),
        heldout_predictive_rms=_rms(predictive),
    )


def standoff_forces(base: Base, model: TwinModel, predictor: Predictor) -> list[float]:
    """Per trajectory of `base`, the force (N) its model (`base.model_for`) finds at the standoff pose where the
    recording is tared (`Predictor.standoff_force`)."""
    return [predictor.standoff_force(base.model_for(model, t), t) for t in base.trajectories]


def by_trajectory(base: Base, heldout: np.ndarray, predictive: np.ndarray, standoff: list[float]) -> list[dict]:
    """Per trajectory of `base`, worst held out first (by its predictive figure): its sensor, id, indenter and path
    ("normal" or "angled"), and the whitened RMS of its residual at the fit ("in_sample"), predicted by the
    nuisances fitted without it ("held_out"; `heldout`, (N,) in `base`'s sample order) and that prediction whitened
    by its predictive spread ("held_out_predictive"; `predictive`); None where none of its samples was predicted;
    "standoff_force" (N; `standoff`) the force at the fit where its recording is tared, and "starts_in_contact" whether
    that exceeds `STANDOFF_LOADED` times the force noise."""
    index = base.residual.trajectory_index

    def rms(values: np.ndarray) -> float | None:
        return _rms(values) if np.isfinite(values).any() else None

    rows = [
        {
            "sensor": t.sensor_id,
            "trajectory": t.trajectory_id,
            "indenter": t.indenter,
            "path": "normal" if t.normal else "angled",
            "in_sample": rms(base.residual.values[index == k]),
            "held_out": rms(heldout[index == k]),
            "held_out_predictive": rms(predictive[index == k]),
            "standoff_force": standoff[k],
            "starts_in_contact": bool(standoff[k] > STANDOFF_LOADED * base.sigma[:3].max()),
        }
        for k, t in enumerate(base.trajectories)
    ]
    worst = "held_out_predictive"
    return sorted(rows, key=lambda row: (row[worst] is None, -(row[worst] or 0.0)))


def _shifted(base: Base, model: TwinModel, predictor: Predictor, model_for: ModelFor) -> np.ndarray:
    """Profiled change of the whitened prediction from `base` to the model of each trajectory by `model_for` (a
    `NuisanceValues.model_for`; NaN where the fe replay failed)."""
    return replace(base, model_for=model_for).shifted(predictor, model)


def _posed(values: NuisanceValues, error: str, axis: int) -> ModelFor:
    """The models of `values` with every trajectory's pose error `error` (a `POSE_STEPS` field of `TwinModel`)
    moved by its step along `axis`."""

    def model_for(model: TwinModel, trajectory: TrajectoryRecord) -> TwinModel:
        at = values.model_for(model, trajectory)
        moved = np.array(getattr(at, error))
        moved[axis] += POSE_STEPS[error]
        return replace(at, **{error: tuple(float(v) for v in moved)})

    return model_for


def _jacobian(base: Base, model: TwinModel, predictor: Predictor, values: NuisanceValues) -> np.ndarray:
    """(N, k) finite-difference sensitivity of `base`'s profiled whitened prediction to each slot: forward
    (backward at an upper bound), and the other way too when the first step's replay fails on samples the
    current values reach (the one that fails on fewer is kept); `base` must be the residual at `values` or
    the nominal one (differences only). The replays of the values, of every first step and of every pose error's
    step are solved as one batch. The registration rotations' and joint offsets' columns come from the registration
    offset's and the pose errors' (`_derived_columns`), on the columns before the PDC gains are profiled out (each
    trajectory's rows its own replays'); every column is profiled last (`GainNuisance.project`, linear)."""
    steps = [() if s.effect in DERIVED else _steps(values, i) for i, s in enumerate(values.slots)]
    first = [values.moved(_along(len(steps), i, tries[0])).model_for for i, tries in enumerate(steps) if tries]
    derived = any(s.effect in DERIVED for s in values.slots)
    posed = {(error, axis): _posed(values, error, axis) for error in POSE_STEPS for axis in range(3)} if derived else {}
    _prefetch(base, model, predictor, [values.model_for, *first, *posed.values()])
    here = _unprofiled(base, model, predictor, values.model_for)
    columns = np.zeros((len(here), len(steps)))
    for i, tries in enumerate(steps):
        tried = []
        for step in tries:
            moved = values.moved(_along(len(steps), i, step))
            tried.append((_unprofiled(base, model, predictor, moved.model_for) - here) / step)
            if np.isfinite(tried[-1]).sum() == np.isfinite(here).sum():
                break
        if tried:
            columns[:, i] = max(tried, key=lambda c: np.isfinite(c).sum())
    if derived:
        shift = {key: _unprofiled(base, model, predictor, model_for) - here for key, model_for in posed.items()}
        pose = {e: np.column_stack([shift[(e, a)] for a in range(3)]) / step for e, step in POSE_STEPS.items()}
        _derived_columns(columns, base, values, pose)
    return _usable(base.nuisance.project(columns))


def _unprofiled(base: Base, model: TwinModel, predictor: Predictor, model_for: ModelFor) -> np.ndarray:
    """`_shifted` before the PDC gains are profiled out (`Base.unprofiled_shift`)."""
    return replace(base, model_for=model_for).unprofiled_shift(predictor, model)


def _derived_columns(columns: np.ndarray, base: Base, values: NuisanceValues, pose: dict[str, np.ndarray]) -> None:
    """Fill the registration rotations' and joint offsets' columns in place by the chain rule: on trajectory k's
    rows, d r / d p = (d r / d offset) (d offset / d p) + (d r / d slope) (d slope / d p) + (d r / d tilt)
    (d tilt / d p), the first factor the registration offset's columns restricted to those rows (a trajectory's
    prediction depends on its own pose only), the next two `pose`'s (N, 3) columns of the pose errors, and the
    second factors `pose_error`'s (linear). Exact on columns before the PDC gains are profiled out: the gain's
    profile couples a sensor's trajectories, each moved by its own d offset / d p (chained after profiling, the
    rotations' and joint offsets' columns were 5-133 % off direct differences on seed 6's realistic null,
    docs/analysis.md)."""
    slots = values.slots
    position = {(s.effect, s.parameter, s.sensor, s.arm): c for c, s in enumerate(slots)}
    index = base.residual.trajectory_index
    for k, trajectory in enumerate(base.trajectories):
        mine = [i for i, slot in enumerate(slots) if slot.effect in DERIVED and slot.applies(trajectory)]
        if not mine:
            continue
        rows = index == k
        axes = [
            position[(REGISTRATION, p.name, trajectory.sensor_id, trajectory.arm)]
            for p in EFFECTS[REGISTRATION].parameters
        ]
        by_error = np.hstack([columns[np.ix_(rows, axes)], pose["path_slope"][rows], pose["indenter_tilt"][rows]])
        chain = pose_jacobian(values.path(trajectory), *values.arm_pose(trajectory))  # (9, 3 rotation + 7 joints)
        for i in mine:
            columns[rows, i] = by_error @ chain[:, _index(slots[i]) + (3 if slots[i].effect == JOINT_OFFSET else 0)]


def _steps(values: NuisanceValues, i: int) -> tuple[float, ...]:
    """Finite-difference steps of slot i to try in turn: forward then backward (backward alone at an upper
    bound), those that stay within its bounds."""
    p = _parameter(values.slots[i])
    size = STEPS.get(values.slots[i].effect, p.scale)  # an effect fitted jointly: its library step
    steps = (size, -size) if values.values[i] + size <= p.upper else (-size,)
    return tuple(step for step in steps if p.lower <= values.values[i] + step <= p.upper)


def _along(k: int, i: int, step: float) -> np.ndarray:
    """(k,) move of `step` along slot i."""
    delta = np.zeros(k)
    delta[i] = step
    return delta


def _prefetch(base: Base, model: TwinModel, predictor: Predictor, candidates: list[ModelFor]) -> None:
    """Solve the replays `_shifted` needs for every one of `candidates` (each a `NuisanceValues.model_for`) as one
    batch (those not cached)."""
    predictor.prefetch_many(
        [request for model_for in candidates for request in model_requests([model], base.trajectories, model_for)]
    )


def _usable(jac: np.ndarray) -> np.ndarray:
    """`jac` with every column finite on fewer than `USABLE_ROWS` of the rows where some column is finite set
    to zero (a replay that failed early: no sensitivity is known there, and its few rows would decide the fit)."""
    reached = np.isfinite(jac).any(axis=1)
    out = jac.copy()
    for i in range(jac.shape[1]):
        if np.isfinite(jac[reached, i]).mean() < USABLE_ROWS:
            out[:, i] = np.where(reached, 0.0, np.nan)
    return out


def _gauss_newton(
    nominal: Base,
    model: TwinModel,
    predictor: Predictor,
    start: NuisanceValues,
    prior: NuisanceValues,
    report: Callable[[str], None],
    settle: bool = False,
) -> Fit:
    """Levenberg-Marquardt (`twin.analysis.fit.gauss_newton`, damping `DAMPING`, each step within `TRUST` prior
    sigmas) from `start`, the priors centred on `prior` (the model's values); stops at the noise, after `ITERATIONS`
    or when a step (solved again more damped up to `BACKTRACKS` times) does not lower the cost: the chi-square plus
    the priors', infinite where the replay fails on samples the nominal model reaches (a fit must not buy a lower
    chi-square by losing samples); past `ITERATIONS` it goes on while each step lowers the cost's excess over the
    noise by a tenth (`EXTRA_ITERATIONS` at most); `settle`: at the noise, on until a step lowers the cost by less
    than the number of nuisances (`GaussNewtonSettings.settle_at_noise`; the fit on the samples its first values
    reached, where a fit stopped at the noise was measured 2.3 % off the plant's skin modulus). Its Jacobian is the last
    sensitivity a step used (at the point before the last step)."""
    gaussian = _prior(prior)

    def residual(at: Parameters) -> np.ndarray:
        return nominal.residual.values - _shifted(nominal, model, predictor, start.at(at).model_for)

    def cost(r: np.ndarray, values: np.ndarray) -> float:
        return float("inf") if np.isnan(r).any() else nominal.nuisance.chi2(r) + gaussian.cost(values)

    hooks = GaussNewtonHooks(
        jacobian=lambda at: _jacobian(nominal, model, predictor, start.at(at)),
        at_noise=lambda r: not np.isnan(r).any() and nominal.noise_test(r, len(start.slots)).is_noise,
        cost=cost,
        on_iteration=lambda i, r: report(f"iteration {i + 1}: RMS {_rms(r):.2f}x the noise"),
    )
    settings = GaussNewtonSettings(
        ITERATIONS,
        BACKTRACKS,
        extra_iterations=EXTRA_ITERATIONS,
        extra_over_noise=True,
        trust=TRUST,
        damping=DAMPING,
        settle_at_noise=settle,
    )
    return gauss_newton(residual, start.parameters, hooks, settings, gaussian)


def _best_starts(
    nominal: Base, model: TwinModel, predictor: Predictor, fitted: NuisanceValues, residual: np.ndarray
) -> NuisanceValues:
    """The fitted values with each arm's registration (and joint offsets) replaced by whichever of its fit, its
    contact-onset start about the fit (`_onset_start`, from the fit's replays) and `REGISTRATION_STARTS` leaves
    that arm's trajectories the least squared residual (one replay set per start: every arm is moved to its
    onset start, or to the same start, at once; the starts' replays solved as one batch)."""
    arms = sorted({(s.sensor, s.arm) for s in fitted.slots if s.effect == REGISTRATION})
    index = nominal.residual.trajectory_index
    trials = [_onset_start(nominal, model, predictor, fitted, arms)]
    trials += [_with_registration(fitted, {arm: offset for arm in arms}) for offset in REGISTRATION_STARTS]
    _prefetch(nominal, model, predictor, [t.model_for for t in trials])  # every start's replays in one batch
    best = {arm: (_arm_cost(residual, index, nominal, arm), fitted) for arm in arms}
    for trial in trials:
        moved = nominal.residual.values - _shifted(nominal, model, predictor, trial.model_for)
        for arm in arms:
            cost = _arm_cost(moved, index, nominal, arm)
            if cost < best[arm][0]:
                best[arm] = (cost, trial)
    chosen = tuple(
        best[(s.sensor, s.arm)][1].values[i] if s.effect in (REGISTRATION, JOINT_OFFSET) else v
        for i, (s, v) in enumerate(zip(fitted.slots, fitted.values, strict=True))
    )
    return replace(fitted, values=chosen)


def _onset_start(
    nominal: Base, model: TwinModel, predictor: Predictor, fitted: NuisanceValues, arms: list[tuple[int, str]]
) -> NuisanceValues:
    """`fitted` moved, arm by arm, to what the contact onsets about it say (`twin.analysis.onset`, from the fit's
    replays): the registration offset alone where the arm has no joint offsets; else the registration offset
    and the joint offsets together, the bounded least squares (`twin.analysis.fit.linear_step`) of each path's
    shift s_k = row_k . (dt + J_k dq) (J_k: `_joint_offset_rows`, the tip where contact begins) with a
    Gaussian prior (`PRIORS`) on the step about the fit, since each pose is off by its own amount."""
    offsets, moved = {}, np.array(fitted.values)
    everything = fitted.parameters
    for arm in arms:
        mine = [t for t in nominal.trajectories if (t.sensor_id, t.arm) == arm]
        estimate = onset_estimate(predictor, [fitted.model_for(model, t) for t in mine], mine, nominal.sigma)
        joints = [i for i, s in enumerate(fitted.slots) if s.effect == JOINT_OFFSET and (s.sensor, s.arm) == arm]
        offsets[arm] = _arm_offset(fitted, arm) + estimate.offset
        used = [(t, shift) for t, shift in zip(mine, estimate.shifts, strict=True) if np.isfinite(shift.std)]
        if joints and used:
            registration = [i for i, s in enumerate(fitted.slots) if _is_arm(s, arm)]  # dx, dy, dz
            at = everything.subset(registration + joints)
            rows = np.array([np.r_[s.row, s.row @ _joint_offset_rows(fitted, t)] / s.std for t, s in used])
            sigma = np.r_[[PRIORS[REGISTRATION]] * len(registration), [PRIORS[JOINT_OFFSET]] * len(joints)]
            step = linear_step(rows, np.array([s.shift / s.std for _, s in used]), at, Prior(at.values, sigma))
            offsets[arm] = _arm_offset(fitted, arm) + step[:3]
            moved[joints] = moved[joints] + step[3:]
    bounds = fitted.parameters
    start = replace(fitted, values=tuple(float(v) for v in np.clip(moved, bounds.lower, bounds.upper)))
    return _with_registration(start, offsets)


def _joint_offset_rows(values: NuisanceValues, trajectory: TrajectoryRecord) -> np.ndarray:
    """(3, 7) m/rad: how the tip where `trajectory`'s commanded depth is zero moves per radian of each joint offset
    about `values`."""
    return pose_jacobian(values.path(trajectory), *values.arm_pose(trajectory))[:3, 3:]


def _arm_offset(values: NuisanceValues, arm: tuple[int, str]) -> np.ndarray:
    """(3,) m: the registration offset of one (sensor, arm) in `values`."""
    return registration_vector(
        {s.parameter: v for s, v in zip(values.slots, values.values, strict=True) if _is_arm(s, arm)}
    )


def _is_arm(slot: Slot, arm: tuple[int, str]) -> bool:
    return slot.effect == REGISTRATION and (slot.sensor, slot.arm) == arm


def _with_registration(values: NuisanceValues, offsets: dict[tuple[int, str], np.ndarray]) -> NuisanceValues:
    """`values` with each (sensor, arm)'s registration set to its offset (m, (3,)) in `offsets`, clipped to
    the effect's bounds."""
    moved = {arm: registration_values(offset) for arm, offset in offsets.items()}
    return replace(
        values,
        values=tuple(
            moved[(s.sensor, s.arm)][s.parameter] if s.effect == REGISTRATION else v
            for s, v in zip(values.slots, values.values, strict=True)
        ),
    )


def _arm_cost(residual: np.ndarray, index: np.ndarray, base: Base, arm: tuple[int, str]) -> float:
    """Sum of squares of the residual on one (sensor, arm)'s trajectories (a failed replay costs infinity)."""
    mine = np.isin(index, [i for i, t in enumerate(base.trajectories) if (t.sensor_id, t.arm) == arm])
    values = residual[mine]
    return float(np.sum(values**2)) if np.isfinite(values).all() else float("inf")


def _leave_one_trajectory_out(
    base: Base, jac: np.ndarray, fitted: NuisanceValues, prior: NuisanceValues
) -> tuple[np.ndarray, np.ndarray]:
    """Each trajectory's residual predicted by the nuisances fitted (linearised at the fit, priors kept) without it,
    and that prediction whitened by its predictive spread (`twin.analysis.fit.predictive_whitened`: the noise plus
    what the other trajectories and the priors leave of the nuisances uncertain), each (N,)."""
    residual = base.residual.values
    index = base.residual.trajectory_index
    raw, predictive = np.full_like(residual, np.nan), np.full_like(residual, np.nan)
    gaussian, scale = _prior(prior), fitted.parameters.scale
    for i in range(len(base.trajectories)):
        test = index == i
        train_jac, train = np.where(test[:, None], np.nan, jac), np.where(test, np.nan, residual)
        delta = linear_step(train_jac, train, fitted.parameters, gaussian)
        raw[test] = residual[test] - jac[test] @ delta
        matrix = reduced(train_jac * scale, train)[0]
        precision = matrix.T @ matrix + np.diag((scale / gaussian.sigma) ** 2)
        predictive[test] = predictive_whitened(raw[test], jac[test] * scale, precision)
    return raw, predictive


def _correlation(jac: np.ndarray, values: NuisanceValues) -> list[list[float]]:
    """Correlations of the fitted nuisances (from the scaled J^T J with the priors)."""
    spread = fit_uncertainty(jac, values.parameters.scale, prior_sigma=_prior(values).sigma)
    return spread.correlation.round(4).tolist()


def _rms(values: np.ndarray) -> float:
    """Whitened RMS, skipping samples without a prediction (NaN)."""
    return float(np.sqrt(np.nanmean(values**2)))


def _profiled_rms(base: Base, values: np.ndarray) -> float:
    """Whitened RMS with the PDC gains' prior cost, as diagnosis reports a base residual."""
    return float(np.sqrt(base.nuisance.chi2(values) / np.sum(np.isfinite(values))))
