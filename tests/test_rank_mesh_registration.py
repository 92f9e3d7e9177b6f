"""A registration offset ranked and refitted on a coarser fe mesh (`twin diagnose --rank-mesh-mm`, issue 18): a coarse
mesh's facets put the skin's contact elsewhere, so its fit of the indenter's path is off on the campaign's own mesh
by more than the noise allows; finished there (`refit.finish_on_model_mesh`) the hidden offset is named.

Measured before the finish (docs/analysis.md, session 25): this campaign's offset fitted (0.211, 0.314, 0.269) mm on
the 2 mm mesh against the plant's (0.244, 0.293, 0.327) mm, 1.46x the noise on the 1 mm mesh: "unexplained". Drawn with
seed 6 (0.413, 0.265, -0.144) mm, the coarse refit ends at 9.0x on the 2 mm mesh and the finish starts from the contact
onsets' estimate (4.76x); with the coarse columns only it ended at 1.44x, 2.26x held out, "unexplained" (session 26,
before the finish took the model mesh's own columns once the coarse ones converge slowly)."""

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.predict import Predictor, TwinModel
from twin.campaign import run_campaign
from twin.demo import CHECK_CONFIG, loop_setup

HIDDEN = "registration_offset"
CONFIG = replace(
    CHECK_CONFIG,
    mesh_max_edge=1e-3,
    settings=replace(CHECK_CONFIG.settings, points_per_indenter=2, normal_depth=2e-3, angled_depth=1e-3),
)
"""Sensor 2, sphere_small and cylinder_long, two points each pressed 2 mm normal and 1 mm at 30 degrees, on a 1 mm
mesh (seed 5 keeps 6 of the 8 presses)."""


@pytest.fixture(scope="module", params=[5, 6], ids=["seed5", "seed6"])
def seed(request: pytest.FixtureRequest) -> int:
    return request.param


@pytest.fixture(scope="module")
def campaign(seed: int, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    config, plant = loop_setup(HIDDEN, seed, CONFIG)
    result = run_campaign(config, tmp_path_factory.mktemp("rank_mesh") / "campaign", workers=2, plant=plant)
    return next(iter(result.files.values())), plant.effects[HIDDEN]


def test_a_registration_offset_ranked_on_a_mesh_twice_as_coarse_is_named_on_the_campaigns(
    campaign: tuple[Path, dict],
) -> None:
    path, truth = campaign
    data = load_campaign(path)
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    found = diagnose([data], model, Predictor(), candidates=[HIDDEN, "skin_thickness"], top=1, rank_mesh=2e-3)
    assert found.ranked_mesh == 2e-3
    assert found.verdict == HIDDEN, found.reason
    best = found.candidates[0]
    assert best.heldout_is_noise and best.refit_rms <= found.rms_threshold, (best.refit_rms, best.heldout_rms)
    fitted = np.array([best.refit_parameters[k] for k in ("dx", "dy", "dz")])
    assert np.abs(fitted - np.array([truth[k] for k in ("dx", "dy", "dz")])).max() < 0.05e-3, fitted
