"""Diagnosis on a plant with a hidden effect: the hidden one ranks first and adding it brings the error down.

The hidden effect's values live only in the plant; the diagnosis sees nothing but the campaign file.
"""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from twin.analysis.data import load_campaign
from twin.analysis.diagnose import NOISE_TOLERANCE, diagnose, fit_effect
from twin.analysis.predict import Predictor, TwinModel
from twin.campaign import QUICK_CONFIG, run_campaign
from twin.plant import make_plant

CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_small", "cylinder_long"))


def _campaign(out: Path, effects: dict) -> Path:
    plant = make_plant(
        [2],
        7,
        variability=0.0,
        mount_rotation_error=0.0,
        mount_translation_error=0.0,
        effects=effects,
        exact_registration=True,
    )
    return run_campaign(CONFIG, out, workers=2, plant=plant).files[2]


@pytest.fixture(scope="module")
def delayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    hidden_seconds = float(np.random.default_rng(11).uniform(0.04, 0.12))
    return _campaign(tmp_path_factory.mktemp("delay"), {"time_delay": {"seconds": hidden_seconds}})


def test_hidden_time_delay_ranks_first_and_its_fit_reaches_the_noise(delayed: Path) -> None:
    data = load_campaign(delayed)
    predictor = Predictor()
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    result = diagnose([data], model, predictor)
    assert result.base_rms > 1.5, "a delay this size must show in the residual"
    assert result.candidates[0].name == "time_delay"
    assert result.verdict == "time_delay", result.reason
    fit = fit_effect([data], model, "time_delay", predictor)
    assert fit.rms_after <= NOISE_TOLERANCE < fit.rms_before
    assert 0.03 <= fit.values["seconds"] <= 0.13
