"""The `twin fe` commands keep their JSON contracts and fail cleanly on bad input."""

import json

import pytest
from typer.testing import CliRunner

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
