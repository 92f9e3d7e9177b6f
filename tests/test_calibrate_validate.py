"""Calibration like the paper (penalty, uncertainty, recovery of a stiffer skin) and its validation metric."""

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from typer.testing import CliRunner

from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS
from twin.analysis.calibrate import (
    CALIBRATED,
    THICKNESS_SMOOTHING,
    THICKNESS_WEIGHT,
    CalibrationSettings,
    _uncertainty,
    _warnings,
    calibrate,
    default_trajectories,
    thickness_penalty,
    thickness_penalty_slope,
)
from twin.analysis.data import load_campaign
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.validate import FORCE_THRESHOLD, trajectory_error
from twin.cli import app
from twin.plant import make_plant

STIFFER_MU = 3.6e5
"""The plant's true skin modulus (Pa): 29 % above the nominal 2.8e5 the calibration starts from."""


def test_the_thickness_term_is_a_smooth_symmetric_penalty() -> None:
    assert thickness_penalty(SENSOR_THICKNESS) == pytest.approx(0.0, abs=1e-12)
    for d in (1e-6, 1e-4, 1e-3):
        assert thickness_penalty(SENSOR_THICKNESS + d) == pytest.approx(thickness_penalty(SENSOR_THICKNESS - d))
    far = 2e-3  # far beyond eps the penalty grows like w2 |dt| - w2 eps
    expected = THICKNESS_WEIGHT * (far - THICKNESS_SMOOTHING)
    assert thickness_penalty(SENSOR_THICKNESS + far) == pytest.approx(expected, rel=0.01)
    near = 0.1 * THICKNESS_SMOOTHING
    quadratic = THICKNESS_WEIGHT * near**2 / (2 * THICKNESS_SMOOTHING)
    assert thickness_penalty(SENSOR_THICKNESS + near) == pytest.approx(quadratic, rel=0.01)


def test_the_thickness_penalty_slope_is_its_derivative_and_vanishes_at_the_target() -> None:
    assert thickness_penalty_slope(SENSOR_THICKNESS) == 0.0
    h = 1e-9
    for d in (-2e-3, -1e-4, -1e-5, 3e-6, 5e-5, 1e-3):
        t = SENSOR_THICKNESS + d
        central = (thickness_penalty(t + h) - thickness_penalty(t - h)) / (2 * h)
        assert thickness_penalty_slope(t) == pytest.approx(central, rel=1e-5)
    assert thickness_penalty_slope(SENSOR_THICKNESS + 1.0) == pytest.approx(THICKNESS_WEIGHT, rel=1e-6)


def test_uncertainty_of_a_linear_fit_matches_least_squares_theory() -> None:
    rng = np.random.default_rng(0)
    jac = rng.normal(size=(400, 4))
    residual = rng.normal(scale=0.2, size=400)
    ranges = np.array([1e-3, 9e5, 0.9, 10.0])
    std, corr, condition = _uncertainty(jac, residual, ranges)
    s2 = residual @ residual / (400 - 4)
    expected = np.sqrt(np.diag(s2 * np.linalg.inv(jac.T @ jac))) * ranges
    assert [std[n] for n in CALIBRATED] == pytest.approx(expected, rel=1e-9)
    assert np.allclose(np.diag(corr), 1.0) and condition < 10
    low, high = np.zeros(4), ranges
    assert _warnings(std, corr, condition, low, high) == []


def test_collinear_parameters_are_flagged() -> None:
    rng = np.random.default_rng(1)
    base = rng.normal(size=(300, 3))
    jac = np.column_stack([base, base[:, 0] * 2.0 + 1e-7 * rng.normal(size=300)])
    std, corr, condition = _uncertainty(jac, rng.normal(size=300), np.ones(4))
    warnings = _warnings(std, corr, condition, np.zeros(4), np.ones(4))
    assert any("ill-conditioned" in w for w in warnings)
    assert any("thickness and fluid_temperature are correlated" in w for w in warnings)


def test_the_validation_error_counts_forces_above_half_a_newton_before_divergence() -> None:
    measured = np.array([[0.0, 0, 0.2], [0, 0, 0.6], [0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0]])
    predicted = measured + np.array([[0, 0, 5.0], [0.3, 0, 0], [0.0, 0.4, 0.0], [0, 0, np.nan], [0, 0, 0.1]])
    trajectory = SimpleNamespace(
        sensor_id=1, trajectory_id=7, indenter="sphere_medium", normal=False, rows={"force": measured}
    )
    error = trajectory_error(trajectory, SimpleNamespace(rows=SimpleNamespace(force=predicted)))
    # Row 0 is below 0.5 N; row 3 diverged, so row 4 (after it) is excluded too: rows 1 and 2 count.
    assert (error.rows_used, error.rows_reached, error.rows_total) == (2, 3, 5)
    assert error.rms_n == pytest.approx(np.sqrt(0.3**2 / 2) + np.sqrt(0.4**2 / 2))
    assert FORCE_THRESHOLD == 0.5 and error.force_max_n == pytest.approx(3.0)


@pytest.fixture(scope="module")
def stiffer_campaign(tmp_path_factory: pytest.TempPathFactory, make_tiny_campaign) -> Path:
    plant = make_plant(
        [2],
        3,
        nominal=SkinParameters(mu_nh=STIFFER_MU),
        variability=0.0,
        mount_rotation_error=0.0,
        mount_translation_error=0.0,
        exact_registration=True,
    )
    return make_tiny_campaign(tmp_path_factory.mktemp("stiffer"), plant, angled_depth=1.0e-3)


def test_calibration_moves_the_modulus_toward_the_plants_and_lowers_the_cost(stiffer_campaign: Path) -> None:
    data = load_campaign(stiffer_campaign)
    chosen = default_trajectories([data])
    assert [t.normal for t in chosen] == [False] and chosen[0].indenter == "sphere_medium"
    base = TwinModel(mesh_max_edge=data.mesh_max_edge)
    result = calibrate(chosen, base, Predictor(), CalibrationSettings(max_iterations=4))
    start_cost = result.history[0]["cost"]
    assert result.cost < 0.7 * start_cost, (start_cost, result.cost)
    nominal = SkinParameters().mu_nh
    assert result.parameters["mu_nh"] > nominal + 0.4 * (STIFFER_MU - nominal), result.parameters
    assert abs(result.thickness - SENSOR_THICKNESS) < 0.1e-3
    assert set(result.intervals) == set(CALIBRATED) and result.evaluations == len(result.history)
    json.dumps(result.to_dict())  # the --json shape is serialisable
    model = result.model(base)
    assert model.inflation == "thermal" and model.skin.mu_nh == result.parameters["mu_nh"]


def test_validate_cli_writes_the_per_indenter_table_and_plots(stiffer_campaign: Path, tmp_path: Path) -> None:
    out = tmp_path / "validation"
    result = CliRunner().invoke(app, ["validate", str(stiffer_campaign), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output.strip().splitlines()[-1])
    assert set(summary["indenters"]) == {"sphere_medium"}
    entry = summary["indenters"]["sphere_medium"]
    assert entry["trajectories"] >= 1 and entry["mean_rms_n"] > 0
    assert {"sensor", "trajectory", "rms_n", "rows_used"} <= set(summary["trajectories"][0])
    assert (out / "validation.json").exists() and (out / "validation_by_indenter.png").stat().st_size > 1000


def test_calibrate_cli_rejects_a_missing_trajectory(stiffer_campaign: Path) -> None:
    result = CliRunner().invoke(app, ["calibrate", str(stiffer_campaign), "--trajectory", "2:999"])
    assert result.exit_code == 2 and "no trajectory 999" in result.output


def test_a_model_json_round_trips_with_its_inflation_rule() -> None:
    model = TwinModel(skin=replace(SkinParameters(), fluid_temperature=31.0), inflation="thermal")
    assert TwinModel.from_dict(json.loads(json.dumps(model.to_dict()))) == model
    with pytest.raises(ValueError, match="inflation"):
        TwinModel(inflation="pumped")
