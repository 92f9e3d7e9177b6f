"""Nuisances first (issue 20): on a realistic plant the standard unknowns are fitted before any effect is
sought; a null ends "nothing beyond the nuisances" and a hidden effect is still named.

The plant is this repository's default realistic one (`make_plant` defaults: 5 % unit-to-unit skin
spread, 10 % friction, simulated registration with the arms' joint offsets, mount placement error, F/T
bias), on the tiny campaign of `conftest.tiny_campaign_file` (sensor 2, sphere_medium, one normal and
one angled path on one arm) pressed 1.5 mm (normal) and 1.0 mm (angled), past the plant's registration error (at
the tiny campaign's own 0.4 / 0.2 mm its indenter never touches this plant's skin, and no effect of the force can
show). The hidden effect, a stream delay of whole samples, is applied to the null campaign's raw F/T streams by
`effect_generator`, code apart from the plant and the analysis. The contact-onset estimate of a registration offset
(`twin.analysis.onset`) is checked on the same paths measured by the model itself with a known 1.0 mm offset.
"""

from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest
from conftest import tiny_campaign_file
from effect_generator import apply_ft_delay

from twin.analysis.data import CampaignData, load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.nuisances import (
    JOINT_OFFSET,
    NUISANCE_EFFECTS,
    REGISTRATION_ROTATION,
    NuisanceValues,
    fit_nuisances,
    nuisance_slots,
)
from twin.analysis.nuisances import _jacobian as nuisance_jacobian
from twin.analysis.onset import onset_estimate
from twin.analysis.pose_error import pose_error
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.refit import refit
from twin.analysis.residual import base_residual
from twin.analysis.sensitivity import linearise
from twin.analysis.verdict import NOTHING_BEYOND_NUISANCES, Candidate
from twin.campaign import CampaignConfig, true_biotac_pose
from twin.cli.loop import _print_diagnosis, _print_nuisances
from twin.effects import EFFECTS, REGISTRATION
from twin.kinematics import forward, rotation_log
from twin.label_truth import true_tip_locations
from twin.plant import Plant, make_plant
from twin.scene import TestbedScene

SEED = 11
DELAY_SAMPLES = 8
"""The generated stream delay (samples at the campaign's 100 Hz: 80 ms, inside the hidden draws' 40-120 ms)."""
CANDIDATES = ["fill_volume", "skin_stiffening", "time_delay", "ft_drift", "ft_gain", "ft_calibration"]
"""Two physics effects (each an fe replay set per parameter) and the F/T chain's (none), to keep the test short."""


KNOWN_OFFSET = {"dx": 0.62e-3, "dy": -0.78e-3, "dz": 0.13e-3}
"""A registration offset of 1.0 mm (m, biotac frame), inside the paper's 0.5-1.5 mm band."""


@pytest.fixture(scope="module")
def predictor() -> Predictor:
    return Predictor()


@pytest.fixture(scope="module")
def deep_paths(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The realistic plant's tiny campaign pressed 1.5 mm (normal) and 1.0 mm (30 degrees): past a 1 mm offset."""
    out = tmp_path_factory.mktemp("deep")
    return tiny_campaign_file(out, make_plant([2], SEED), angled_depth=1.0e-3, normal_depth=1.5e-3)


def measured_by(model: TwinModel, data: CampaignData, predictor: Predictor, seed: int = 0) -> CampaignData:
    """`data`'s paths as `model` itself measures them: each trajectory's raw F/T force and PDC replaced by the
    model's replay plus white noise (0.01 N per force axis in the sensor frame, 1 count of PDC, rounded)."""
    rng = np.random.default_rng(seed)
    records = []
    for t in data.trajectories:
        p = predictor.predict(model, t)
        wrench = t.raw.wrench.copy()
        noise = 0.01 * rng.standard_normal((len(wrench), 3))
        wrench[:, :3] = wrench[0, :3] + p.force_fullrate @ t.sensor_in_biotac[:3, :3] + noise
        pdc = np.round(t.raw.pdc[0] + p.pdc_fullrate + rng.standard_normal(len(wrench)))
        records.append(replace(t, raw=replace(t.raw, wrench=wrench, pdc=pdc)))
    return replace(data, trajectories=records)


def test_the_contact_onset_finds_a_known_registration_offset_and_the_refit_reaches_it(
    deep_paths: Path, predictor: Predictor
) -> None:
    """The model measures its own paths with a 1.0 mm offset: each press's contact shift is the first-order
    geometric one, n.o / n.d, the estimate sees the skin normal's component of the offset and no more (one
    point: the other two directions are reported unseen and left at zero), and the refit linearised there
    reaches the noise within 0.1 mm of the offset on every axis (the 1 mm starts ended at 8.5x on a plant).
    Naming needs two points (docs/analysis.md: with one, dy and dz correlate 0.984)."""
    data = load_campaign(deep_paths)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    offset = np.array(list(KNOWN_OFFSET.values()))
    measured = measured_by(model.with_effects({REGISTRATION: KNOWN_OFFSET}), data, predictor)
    base = base_residual([measured], model, predictor)
    estimate = onset_estimate(predictor, [model] * 2, measured.trajectories, base.sigma)
    for shift in estimate.shifts:
        assert shift.shift == pytest.approx(shift.row @ offset, abs=0.05e-3), estimate.to_dict()
    assert len(estimate.unseen) == 2, estimate.to_dict()
    assert np.abs(estimate.unseen @ estimate.offset).max() < 1e-12, "an unseen direction must not be invented"
    normal = estimate.shifts[0].normal
    assert normal @ estimate.offset == pytest.approx(normal @ offset, abs=0.05e-3)
    effect = EFFECTS[REGISTRATION]
    start = estimate.values(effect.values())
    lin = linearise(effect, model, start, predictor, base)
    candidate = Candidate(REGISTRATION, "physics", start, 0.0, 0.0, 0.0)
    refit(candidate, model, predictor, base, lin)
    threshold = base.noise_test(base.residual.values).rms_threshold
    assert candidate.refit_rms <= threshold, (candidate.refit_rms, candidate.refit_parameters)
    for axis, value in KNOWN_OFFSET.items():
        assert candidate.refit_parameters[axis] == pytest.approx(value, abs=0.1e-3), candidate.refit_parameters


def plant_registration_error(path: Path, plant: Plant) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per arm, the rigid error of the campaign's registration against the plant's true BioTac pose, as the nuisance
    fit parameterises it: (translation m, rotation vector rad), biotac frame, x_true = R x_estimated + t."""
    truth = true_biotac_pose(plant, 2, TestbedScene(CampaignConfig().scene))
    error = {}
    for t in load_campaign(path).trajectories:
        moved = np.linalg.inv(truth) @ t.registration
        error[t.arm] = (moved[:3, 3], rotation_log(moved[:3, :3]))
    return error


def plant_values(path: Path, plant: Plant, data: CampaignData, rotation: bool = True) -> NuisanceValues:
    """The nuisance slots of `data` at the plant's own values (its skin against the nominal, its registration error,
    its arms' joint offsets; `rotation=False`: the registration rotation left at zero)."""
    skin, nominal = plant.sensor(2).skin, TwinModel().skin
    error = plant_registration_error(path, plant)
    scales = {
        "skin_thickness": skin.thickness / nominal.thickness,
        "skin_modulus": skin.mu_nh / nominal.mu_nh,
        "indenter_friction": skin.friction / nominal.friction,
    }
    values = []
    for slot in nuisance_slots(data.trajectories):
        if slot.effect in scales:
            values.append(scales[slot.effect])
        elif slot.effect == REGISTRATION:
            values.append(error[slot.arm][0]["xyz".index(slot.parameter[1])])
        elif slot.effect == REGISTRATION_ROTATION:
            values.append(error[slot.arm][1]["xyz".index(slot.parameter[1])] if rotation else 0.0)
        else:
            values.append(plant.joint_offset(slot.arm)[int(slot.parameter[1:]) - 1])
    return NuisanceValues(nuisance_slots(data.trajectories), tuple(float(v) for v in values))


def test_the_pose_error_at_the_plants_values_is_where_its_indenter_really_was(deep_paths: Path) -> None:
    """The realistic plant's arm has joint zero offsets and its registration is off by a rigid motion, so each press
    is off by its own amount (docs/analysis.md). `twin.label_truth` rebuilds the plant's true tips by exact forward
    kinematics through the true BioTac pose, code apart from the analysis; the pose error at the plant's values
    (offset where the depth is zero, plus the slope times each row's commanded depth) must put every row's tip there
    within 2 um, and the indenter's tilt must be the true tool rotation's within 0.02 mrad."""
    plant = make_plant([2], SEED)
    true = true_tip_locations(deep_paths, plant=plant)
    with h5py.File(deep_paths, "r") as f:
        label, row_trajectory = f["contact_loc/data"][:], f["trajectory_id/data"][:]
    data = load_campaign(deep_paths)
    values = plant_values(deep_paths, plant, data)
    to_true = np.linalg.inv(true_biotac_pose(plant, 2, TestbedScene(CampaignConfig().scene)))
    apart = []
    for t in data.trajectories:
        rows = row_trajectory == t.trajectory_id
        translation, _ = plant_registration_error(deep_paths, plant)[t.arm]
        error = pose_error(values.path(t), *values.arm_pose(t))
        depth = (label[rows] - t.touch_point) @ t.direction
        predicted = label[rows] + translation + error.offset + np.outer(depth, error.slope)
        assert np.abs(predicted - true[rows]).max() < 2e-6, np.abs(predicted - true[rows]).max()
        apart.append(true[rows].mean(axis=0) - label[rows].mean(axis=0))
        q = t.raw.joints.mean(axis=0)
        estimated = np.linalg.inv(t.registration)[:3, :3] @ forward(t.arm, q, t.tool_tip)[:3, :3]
        real = to_true[:3, :3] @ forward(t.arm, q + plant.joint_offset(t.arm), t.tool_tip)[:3, :3]
        assert rotation_log(real @ estimated.T) == pytest.approx(error.tilt, abs=2e-5)
    assert np.linalg.norm(apart[0] - apart[1]) > 0.1e-3, apart  # the two poses really are off by different amounts


def test_the_chained_pose_columns_are_the_direct_differences(deep_paths: Path, predictor: Predictor) -> None:
    """The registration rotations' and joint offsets' sensitivities come by the chain rule through each press's pose
    error; they must be what replaying the pose itself gives: central differences of 40 urad (tip moves of
    microns), per column within 15 % (of 1 % of the largest, for a column without a signature: the last joint turns a
    sphere about its own axis; the chain's registration and pose columns are forward differences). Chained
    after the PDC gains were profiled out (which couples the presses of a sensor) they were 5-133 % off on seed 6's
    realistic null (docs/analysis.md, session 32)."""
    data = load_campaign(deep_paths)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    base = base_residual([data], model, predictor)
    values = plant_values(deep_paths, make_plant([2], SEED), data)
    jacobian = nuisance_jacobian(base, model, predictor, values)
    step = 4e-5
    derived = [i for i, slot in enumerate(values.slots) if slot.effect in (REGISTRATION_ROTATION, JOINT_OFFSET)]
    errors, norms = {}, {}
    for i in derived:
        delta = np.zeros(len(values.slots))
        delta[i] = step
        plus, minus = (replace(base, model_for=values.moved(d).model_for) for d in (delta, -delta))
        direct = (plus.shifted(predictor, model) - minus.shifted(predictor, model)) / (2 * step)
        finite = np.isfinite(direct) & np.isfinite(jacobian[:, i])
        assert finite.mean() > 0.9, values.slots[i].label
        label = values.slots[i].label
        errors[label] = np.linalg.norm(jacobian[finite, i] - direct[finite])
        norms[label] = np.linalg.norm(direct[finite])
    floor = 0.01 * max(norms.values())  # the last joint turns a sphere about its own axis: no signature to compare
    relative = {label: float(errors[label] / max(norms[label], floor)) for label in errors}
    assert max(relative.values()) < 0.15, relative


@pytest.fixture(scope="module")
def deep_cylinder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """`deep_paths` pressed with the long cylinder, whose flat length feels a tilt (registration rotation of this
    plant's left arm: (1.5, 4.3, -2.0) mrad)."""
    out = tmp_path_factory.mktemp("cylinder")
    plant = make_plant([2], SEED)
    return tiny_campaign_file(out, plant, angled_depth=1.0e-3, normal_depth=1.5e-3, indenter="cylinder_long")


def test_the_nuisance_model_at_the_plants_own_values_explains_its_campaign(
    deep_cylinder: Path, predictor: Predictor
) -> None:
    """Is the nuisance model adequate? At the plant's own values (skin, registration error, joint offsets: what a
    perfect fit would find) its replays of a long cylinder's presses must leave noise (0.996x); with the
    registration's rotation left out (the indenter not tilted, the press not turned by it) they must not (1.22x):
    the test can fail."""
    plant = make_plant([2], SEED)
    data = load_campaign(deep_cylinder)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    nominal = base_residual([data], model, predictor)
    for rotation in (True, False):
        values = plant_values(deep_cylinder, plant, data, rotation)
        base = base_residual([data], model, predictor, values.model_for, sigma=nominal.sigma)
        at_noise = base.noise_test(base.residual.values, 0).is_noise
        assert at_noise == rotation, (rotation, float(np.sqrt(np.nanmean(base.residual.values**2))))


def test_a_realistic_null_is_nothing_beyond_the_nuisances(
    deep_paths: Path, predictor: Predictor, capsys: pytest.CaptureFixture[str]
) -> None:
    """The two presses of the realistic plant, nothing hidden: far from the noise without the nuisances, at it with
    them (in sample, and held out by the predictive spread: two presses leave most of the arm's pose to the priors),
    so the verdict is "nothing beyond the nuisances"; what the campaign cannot tell from them is said."""
    data = load_campaign(deep_paths)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    plain = diagnose([data], model, predictor, candidates=[], top=0)
    assert plain.base_rms > 2.0 * plain.rms_threshold, "the nuisances must show without their fit"
    found = diagnose([data], model, predictor, CANDIDATES, top=1, nuisances=True)
    summary = found.nuisances
    assert found.verdict == NOTHING_BEYOND_NUISANCES, found.reason
    assert summary["heldout_is_noise"] and summary["rms_after"] <= found.rms_threshold, summary
    assert summary["rms_before"] == pytest.approx(plain.base_rms, rel=1e-9)
    assert {"sensor 2 skin_modulus.scale", "sensor 2 left registration_offset.dx"} <= set(summary["values"])
    assert not {c.name for c in found.candidates} & set(NUISANCE_EFFECTS)
    # One point, two paths: more fluid (pretension) looks like a stiffer, thinner skin; a delay does not.
    assert "fill_volume" in summary["cannot_tell_apart"], summary["confounded"]
    assert summary["confounded"]["time_delay"] < 0.5, summary["confounded"]
    _print_nuisances(summary)  # what `twin diagnose --nuisances` prints of it
    printed = capsys.readouterr().out
    assert f"{summary['rms_before']:.2f} -> {summary['rms_after']:.2f}" in printed and "fill_volume" in printed


def test_a_hidden_delay_on_a_realistic_plant_is_named(
    deep_paths: Path, predictor: Predictor, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An 80 ms delay on the realistic plant's two presses: the nuisances, fitted with it in the data, take part of it
    (10.6x -> 1.99x; a delay during a constant-speed press looks like a depth offset), the delay ranks first about
    them, and refitted jointly with them it brings the residual to the noise in sample and held out: named, its
    value within 10 ms, and the nuisances alone were not the noise."""
    delayed = load_campaign(apply_ft_delay(deep_paths, tmp_path / "delayed.hdf5", DELAY_SAMPLES))
    model = TwinModel(mesh_max_edge=delayed.mesh_max_edge)
    found = diagnose([delayed], model, predictor, CANDIDATES, top=1, nuisances=True)
    assert found.verdict == "time_delay", found.reason
    seconds = found.candidates[0].refit_parameters["seconds"]
    rate = delayed.trajectories[0].rate_hz
    assert seconds == pytest.approx(DELAY_SAMPLES / rate, abs=0.01)
    assert np.isfinite(found.nuisances["rms_after"]) and found.nuisances["rms_after"] > found.rms_threshold
    joint = found.to_dict()["jointly"]  # the joint fit's own figures, as `twin diagnose --json` gives them
    assert joint["effect"] == "time_delay" and joint["named"], joint
    assert joint["is_noise"] and joint["heldout_is_noise"] and joint["rms_after"] <= found.rms_threshold, joint
    assert joint["values"]["time_delay.seconds"] == seconds
    _print_diagnosis(found, model.mesh_max_edge)  # what `twin diagnose --nuisances` prints
    printed = capsys.readouterr().out
    assert f"time_delay, fitted jointly with the nuisances: RMS {joint['rms_after']:.2f}" in printed, printed


@pytest.fixture(scope="module")
def paper_depth_presses(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The realistic plant of seed 0 pressed to the paper's depths (3 mm normal, 1.5 mm angled; 0.5 s pauses), where
    the nominal model's replay of the normal press stops early (its fe does not converge that deep)."""
    return tiny_campaign_file(
        tmp_path_factory.mktemp("paper_depth"), make_plant([2], 0), angled_depth=1.5e-3, normal_depth=3e-3, pause_s=0.5
    )


def test_the_nuisances_are_fitted_on_every_sample_their_values_reach(
    paper_depth_presses: Path, predictor: Predictor, capsys: pytest.CaptureFixture[str]
) -> None:
    """A fit judged only on the samples the nominal replay reached leaves the rest of a press out of its chi-square
    (measured before the refit on reached samples: 1.06x on those, 3.66x on all, the skin thickness 5.9 % and modulus
    8.7 % off the plant's). Fitted again on what its values reach, and settled there (on at the noise while a step
    still lowers the cost by the number of nuisances or more), the fit is near the noise on every sample and recovers
    the plant's own skin (its draw, `make_plant`), which the analysis never reads: within 0.1 % (session 33; stopped at
    the noise, the modulus was 2.3 % off)."""
    data = load_campaign(paper_depth_presses)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    nominal = base_residual([data], model, predictor)
    fit = fit_nuisances([data], model, predictor)
    reached = sum(int(m.sum()) for m in fit.base.masks)
    assert reached > sum(int(m.sum()) for m in nominal.masks), "the nominal replay must stop early on this campaign"
    assert fit.rms_after < 1.1, fit.to_dict()
    truth, nominal_skin = make_plant([2], 0).sensor(2).skin, model.skin
    values = fit.values.as_dict()
    for effect, field, tolerance in (
        ("skin_thickness", "thickness", 0.005),
        ("skin_modulus", "mu_nh", 0.005),
        ("indenter_friction", "friction", 0.01),
    ):
        expected = getattr(truth, field) / getattr(nominal_skin, field)
        assert values[f"sensor 2 {effect}.scale"] == pytest.approx(expected, rel=tolerance), (effect, values)
    # Two presses cannot fix the arm's pose: each predicted from the other alone is far off (5.3x, session 33; 140x
    # before the chained pose columns were mended), but within what the other leaves uncertain (its predictive
    # spread: 0.99x), which is what the held-out test asks.
    # Which press fails is said per trajectory, worst first, and printed.
    assert fit.heldout_rms > 3.0 and fit.heldout_is_noise, (fit.heldout_rms, fit.heldout_predictive_rms)
    pressed = fit.heldout_by_trajectory
    assert sorted((p["trajectory"], p["path"]) for p in pressed) == sorted(
        (t.trajectory_id, "normal" if t.normal else "angled") for t in data.trajectories
    )
    held = [p["held_out_predictive"] for p in pressed]
    assert held == sorted(held, reverse=True), held
    assert min(held) <= fit.heldout_predictive_rms <= max(held), (held, fit.heldout_predictive_rms)
    assert all(p["in_sample"] < 1.2 for p in pressed), pressed
    _print_nuisances(fit.to_dict())
    printed = capsys.readouterr().out
    said = f"held out {fit.heldout_rms:.2f}; {fit.heldout_predictive_rms:.2f} of its"
    assert said in printed and "passes the noise test" in printed, printed
    _print_nuisances({**fit.to_dict(), "heldout_is_noise": False})  # as a fit that does not hold out prints it
    printed = capsys.readouterr().out
    worst = pressed[0]
    said = f"trajectory {worst['trajectory']} ({worst['indenter']}, {worst['path']}) {worst['held_out']:.2f}x"
    assert said in printed, printed
