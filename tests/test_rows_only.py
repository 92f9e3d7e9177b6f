"""Row-only files (issue 20, "the data users have"): `twin compare` / `twin validate` / `twin diagnose` on the
paper's public layout, presses derived from the rows alone.

References are independent of the row-only code: the campaign's own trajectory metadata (planned press
directions, touch points, depths), the same campaign analysed from its raw streams, and hand-made press paths.
"""

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from paper_layout import paper_copy, repo_rows_copy
from typer.testing import CliRunner

from twin.analysis.compare import compare
from twin.analysis.data import load_campaign
from twin.analysis.diagnose import diagnose
from twin.analysis.predict import Predictor, TwinModel
from twin.analysis.rows_only import RAW_ONLY_EFFECTS, segment_presses
from twin.analysis.validate import validate
from twin.cli import app


def _campaign(out: Path, hidden: dict | None = None) -> Path:
    """Sensor 2 of a plant without nuisances (`hidden` effects in it), sphere_medium: a 0.8 mm normal press and a
    0.5 mm press tilted 30 degrees at the same point (the second starts within 1 mm of where the first ends), 0.1 s
    pauses, 2 mm mesh."""
    from twin.campaign import QUICK_CONFIG, run_campaign
    from twin.plant import make_plant
    from twin.protocol import QUICK_SETTINGS

    plant = make_plant(
        [2],
        seed=0,
        effects=hidden,
        variability=0.0,
        mount_rotation_error=0.0,
        mount_translation_error=0.0,
        exact_registration=True,
    )
    settings = replace(QUICK_SETTINGS, normal_depth=0.8e-3, angled_depth=0.5e-3, pause_s=0.1)
    config = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_medium",), settings=settings)
    return run_campaign(config, out, workers=1, plant=plant).files[2]


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _campaign(tmp_path_factory.mktemp("rows"))


@pytest.fixture(scope="module")
def copies(campaign: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    paper, repo = tmp_path_factory.mktemp("paper"), tmp_path_factory.mktemp("repo")
    return paper_copy(campaign, paper / "biotac2.hdf5"), repo_rows_copy(campaign, repo / "biotac2.hdf5")


def test_presses_separate_where_a_press_turns_inward_again() -> None:
    """A normal press out to its standoff, then an angled one from 0.5 mm away: no jump, one indenter."""
    step = 1e-4
    normal, tilted = np.array([0.0, 0.0, 1.0]), np.array([np.sin(0.5), 0.0, np.cos(0.5)])
    first = [k * step * normal for k in (*range(8), *range(6, -1, -1), -10)]
    start = np.array([0.0, 0.0, -0.5e-3])
    second = [start + k * step * tilted for k in (*range(5), *range(3, -1, -1), -10)]
    location = np.array(first + second)
    press = segment_presses(location, np.zeros(len(location), int))
    np.testing.assert_array_equal(press, np.repeat([0, 1], [len(first), len(second)]))


def test_presses_match_the_campaign_metadata(campaign: Path, copies: tuple[Path, Path]) -> None:
    full, rows = load_campaign(campaign), load_campaign(copies[0])
    assert rows.rows_only and not full.rows_only
    assert [t.indenter for t in rows.trajectories] == [t.indenter for t in full.trajectories]
    for planned, derived in zip(full.trajectories, rows.trajectories, strict=True):
        assert len(derived.rows["depth"]) == len(planned.rows["depth"])
        assert np.degrees(np.arccos(planned.direction @ derived.direction)) < 2.0
        assert np.linalg.norm(planned.touch_point - derived.touch_point) < 0.1e-3
        np.testing.assert_allclose(derived.rows["depth"], planned.rows["depth"], atol=0.05e-3)
        assert derived.normal == planned.normal


def test_rows_only_figures_match_the_raw_streams_and_both_layouts(campaign: Path, copies: tuple[Path, Path]) -> None:
    predictor, model = Predictor(), TwinModel(mesh_max_edge=2e-3)
    full, paper, repo = (load_campaign(p) for p in (campaign, *copies))
    errors = {name: validate([d], model, predictor) for name, d in (("full", full), ("paper", paper), ("repo", repo))}
    normal = {name: v.trajectories[0] for name, v in errors.items()}
    assert normal["paper"].rows_used >= 3 and np.isfinite(normal["paper"].rms_n)
    assert normal["full"].rms_n < 0.1  # N: no nuisance in the plant, the nominal model is close
    assert normal["paper"].rms_n == pytest.approx(normal["full"].rms_n, rel=0.3)
    assert json.dumps(errors["paper"].to_dict()) == json.dumps(errors["repo"].to_dict())
    noise_full = compare([full], model, predictor).noise
    noise_rows = compare([paper], model, predictor).noise
    for channel in ("force_x", "force_y", "force_z"):
        assert 0.5 < noise_rows[channel] / noise_full[channel] < 3.0  # 30 rows; an upper bound where F curves


def test_validate_cli_on_a_paper_file_names_what_it_cannot_identify(copies: tuple[Path, Path]) -> None:
    result = CliRunner().invoke(app, ["validate", str(copies[0]), "--json"])
    assert result.exit_code == 0, result.output
    assert "rows only" in result.stderr and all(name in result.stderr for name in RAW_ONLY_EFFECTS)
    assert "public meshes in order" in result.stderr  # the paper's files do not name their indenters
    summary = json.loads(result.stdout[result.stdout.index("{") :])
    assert np.isfinite(summary["indenters"]["sphere_medium"]["mean_rms_n"])


def test_diagnose_on_paper_files_finds_a_hidden_skin_and_says_nothing_on_a_null(
    copies: tuple[Path, Path], tmp_path: Path
) -> None:
    """The loop on the data users have: rows only, in the paper's layout. A skin 15 % thinner in the plant is
    named; the null campaign's rows give "nothing"; effects rows cannot identify are not tried (asked for: a
    one-line error)."""
    predictor, model = Predictor(), TwinModel(mesh_max_edge=2e-3)
    thin = paper_copy(_campaign(tmp_path / "thin", {"skin_thickness": {"scale": 0.85}}), tmp_path / "biotac2.hdf5")
    found = diagnose([load_campaign(thin)], model, predictor, top=1)
    assert found.verdict == "skin_thickness", found.reason
    assert found.candidates[0].refit_parameters["scale"] == pytest.approx(0.85, abs=0.05)
    assert not {c.name for c in found.candidates} & set(RAW_ONLY_EFFECTS)
    null = diagnose([load_campaign(copies[0])], model, predictor, top=1)
    assert null.verdict == "nothing", null.reason
    with pytest.raises(ValueError, match="row-only file cannot identify time_delay"):
        diagnose([load_campaign(copies[0])], model, predictor, candidates=["time_delay", "skin_modulus"])
