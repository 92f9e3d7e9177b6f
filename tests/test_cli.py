"""The `twin fe` commands keep their JSON contracts and fail cleanly on bad input."""

import json
import re
from pathlib import Path

import pytest
from typer.testing import CliRunner

from fe.params import SkinParameters
from twin.analysis.predict import TwinModel
from twin.cli import app

runner = CliRunner()


def _json(args: list[str]) -> list[dict]:
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    return json.loads(result.stdout.strip().splitlines()[-1])


def test_balloon_json_contract() -> None:
    records = _json(
        [
            "fe",
            "balloon",
            "--radius-mm",
            "10",
            "--thickness-mm",
            "0.1",
            "--mu-pa",
            "1e5",
            "--volume-ratios",
            "1.2,1.5",
            "--subdivisions",
            "2",
            "--json",
        ]
    )
    assert [r["volume_ratio"] for r in records] == [1.2, 1.5]
    assert all({"volume_ratio", "stretch", "pressure_pa"} <= set(r) for r in records)
    assert records[1]["pressure_pa"] > records[0]["pressure_pa"] > 0


def test_dome_json_contract() -> None:
    records = _json(
        [
            "fe",
            "dome",
            "--radius-mm",
            "10",
            "--thickness-mm",
            "0.1",
            "--mu-pa",
            "1e5",
            "--volume-ratio",
            "1.3",
            "--indenter-radius-mm",
            "4",
            "--depth-mm",
            "1",
            "--step-mm",
            "0.5",
            "--mesh-mm",
            "1.5",
            "--json",
        ]
    )
    assert [r["depth_mm"] for r in records] == pytest.approx([0.0, 0.5, 1.0], abs=1e-9)
    keys = {"depth_mm", "force_n", "pressure_pa", "volume_m3", "contact_radius_mm"}
    assert all(keys <= set(r) for r in records)
    assert records[0]["force_n"] == 0.0 < records[1]["force_n"] < records[2]["force_n"]
    assert abs(records[2]["volume_m3"] / records[0]["volume_m3"] - 1) < 1e-6
    assert records[0]["contact_radius_mm"] == 0.0 < records[1]["contact_radius_mm"] < records[2]["contact_radius_mm"]


def test_indent_json_contract() -> None:
    records = _json(
        [
            "fe",
            "indent",
            "--indenter",
            "sphere_large",
            "--point-mm",
            "-6,0,-9",
            "--depth-mm",
            "0.2",
            "--step-mm",
            "0.1",
            "--mesh-mm",
            "2.5",
            "--json",
        ]
    )
    assert [round(r["depth_mm"], 6) for r in records] == [0.0, 0.1, 0.2]
    keys = {
        "depth_mm",
        "force_n",
        "pressure_pa",
        "volume_m3",
        "contact_area_mm2",
        "newton_iters",
        "converged",
        "wall_s",
    }
    assert all(keys <= set(r) and len(r["force_n"]) == 3 for r in records)
    assert records[-1]["force_n"][2] > 0


def test_bad_input_exits_with_a_message() -> None:
    result = runner.invoke(app, ["fe", "indent", "--indenter", "teapot", "--mesh-mm", "3"])
    assert result.exit_code == 2
    assert "teapot" in result.output
    result = runner.invoke(app, ["fe", "indent", "--point-mm", "1,2", "--mesh-mm", "3"])
    assert result.exit_code == 2
    result = runner.invoke(app, ["fe", "indent", "--device", "cuda:99", "--mesh-mm", "3"])
    assert result.exit_code == 2 and "'cuda:99' is not available" in result.output


INDENT = ["fe", "indent", "--indenter", "sphere_large", "--point-mm", "-6,0,-9", "--depth-mm", "0.2"]
INDENT += ["--step-mm", "0.1"]
"""A short indentation (three increments) for the coarse --model runs."""


def test_indent_refined_about_its_point_has_more_vertices_and_pushes_back() -> None:
    """`--refine-levels` halves the skin's edges about the press point: more skin vertices, the same JSON."""
    counts = []
    for refine in ([], ["--refine-levels", "1", "--refine-radius-mm", "4"]):
        result = runner.invoke(app, [*INDENT, "--mesh-mm", "2.5", *refine, "--json"])
        assert result.exit_code == 0, result.output
        counts.append(int(re.search(r"inflated (\d+) skin vertices", result.output).group(1)))
        records = json.loads(result.stdout.strip().splitlines()[-1])
        assert all(r["converged"] for r in records) and records[-1]["force_n"][2] > 0
    assert counts[1] > counts[0]


def _model_file(path: Path, model: TwinModel) -> Path:
    path.write_text(json.dumps(model.to_dict()))
    return path


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "cannot read the model"),
        ("{nope", "is not a model JSON"),
        ('{"skin": {}}', "KeyError('mesh_max_edge')"),
        ('{"skin": {"mu_nh": -1}, "mesh_max_edge": 0.002}', "mu_nh=-1 is outside its physical range"),
        ('{"skin": {}, "effects": {"wobble": {}}, "mesh_max_edge": 0.002}', "unknown effect 'wobble'"),
        ('{"skin": {}, "effects": ["wobble"], "mesh_max_edge": 0.002}', "is not a model JSON"),
    ],
)
def test_indent_rejects_a_bad_model_with_one_line(tmp_path: Path, content: str | None, message: str) -> None:
    path = tmp_path / "model.json"
    if content is not None:
        path.write_text(content)
    result = runner.invoke(app, ["fe", "indent", "--model", str(path)])
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2 and len(errors) == 1 and message in errors[0], result.output


def test_indent_model_skin_sets_the_force(tmp_path: Path) -> None:
    """A --model twice as stiff (in its skin, or as the skin_modulus effect) pushes back harder at every depth;
    the model's mesh size is used unless --mesh-mm overrides it."""
    nominal = _json([*INDENT, "--mesh-mm", "2", "--device", "cpu", "--json"])
    stiff = TwinModel(SkinParameters(mu_nh=2 * SkinParameters().mu_nh), mesh_max_edge=2e-3)
    stiff_skin = _json([*INDENT, "--model", str(_model_file(tmp_path / "s.json", stiff)), "--json"])
    doubled = TwinModel(effects={"skin_modulus": {"scale": 2.0}}, mesh_max_edge=3e-3)
    by_effect = _json([*INDENT, "--model", str(_model_file(tmp_path / "e.json", doubled)), "--mesh-mm", "2", "--json"])
    assert all(r["converged"] for r in nominal + stiff_skin + by_effect)
    for soft, hard, effect in zip(nominal[1:], stiff_skin[1:], by_effect[1:], strict=True):
        assert hard["force_n"][2] > 1.2 * soft["force_n"][2] > 0
        assert effect["force_n"] == pytest.approx(hard["force_n"], rel=1e-9, abs=1e-12)


def test_indent_times_a_relaxing_skin_by_its_speed(tmp_path: Path) -> None:
    """A viscoelastic skin indented slowly has relaxed more, so it pushes back less at the same depth."""
    relaxing = TwinModel(SkinParameters(relaxation_fraction=0.3, relaxation_time_s=1.0), mesh_max_edge=2e-3)
    args = [*INDENT, "--model", str(_model_file(tmp_path / "r.json", relaxing)), "--json"]
    fast = _json([*args, "--speed-mm-s", "10"])
    slow = _json([*args, "--speed-mm-s", "0.02"])
    assert all(r["converged"] for r in fast + slow)
    assert 0 < slow[-1]["force_n"][2] < fast[-1]["force_n"][2]
