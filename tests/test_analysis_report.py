"""The comparison report: tables and breakdowns on planted residuals, the files it writes, `twin compare`."""

from __future__ import annotations

import base64
import io
import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread
from typer.testing import CliRunner

from assets.biotac import make_biotac
from twin.analysis.compare import PHASES, Comparison, SampleTable
from twin.analysis.predict import TwinModel
from twin.analysis.report import ReportFiles, write_report
from twin.analysis.report.field import KERNEL_REACH, residual_field
from twin.analysis.report.figures import FIGURES
from twin.analysis.report.stats import depth_bins, depth_step_mm, filtered_noise_gain
from twin.cli import app
from twin.cli.common import model_or_nominal
from twin.processing import lowpass

MESH = 2e-3
RATE_HZ = 100.0
NOISE = {"force_x": 0.01, "force_y": 0.012, "force_z": 0.008, "pdc": 1.5}
INDENTER_FORCE_X = {"sphere": 0.1, "cube": -0.3}  # planted force_x residual per indenter (N)
SENSOR_FORCE_Y = {1: 0.0, 2: 0.2}  # planted force_y residual per sensor (N)
FORCE_Z_PER_DEPTH = 100.0  # planted force_z residual per metre of depth (N/m)
ANGLED_PDC = 5.0  # planted pdc residual of angled trajectories (counts)
PHASE_FORCE_X = (0.01, 0.05, -0.02)  # planted full-rate force_x residual per phase (N)
DEPTHS = np.r_[np.arange(0, 11), np.arange(9, -1, -1)] * 1e-4  # one trajectory's rows: load, unload (m)
NOT_CONVERGED = 3  # last rows of the last trajectory without a prediction
runner = CliRunner()


def _skin_points() -> tuple[np.ndarray, np.ndarray]:
    """Two ventral skin vertices far apart (m): near the tip and near the proximal end."""
    skin = make_biotac(MESH).skin
    ventral = np.flatnonzero(skin.ventral)
    x = skin.vertices[ventral, 0]
    return skin.vertices[ventral[np.argmax(x)]], skin.vertices[ventral[np.argmin(x)]]


def _rows(tip: np.ndarray, proximal: np.ndarray) -> SampleTable:
    """Rows of 8 trajectories: 2 sensors x 2 indenters x normal/angled; spheres at `tip`, cubes at `proximal`."""
    labels: dict[str, list] = {k: [] for k in ("sensor", "trajectory", "indenter", "normal", "depth", "phase", "time")}
    contacts = []
    for k, (sensor, indenter, normal) in enumerate(
        (s, i, n) for s in (1, 2) for i in ("sphere", "cube") for n in (True, False)
    ):
        n_rows = len(DEPTHS)
        labels["sensor"].append(np.full(n_rows, sensor))
        labels["trajectory"].append(np.full(n_rows, k))
        labels["indenter"].append(np.full(n_rows, indenter, dtype=object))
        labels["normal"].append(np.full(n_rows, normal))
        labels["depth"].append(DEPTHS)
        labels["phase"].append(np.where(np.arange(n_rows) > np.argmax(DEPTHS), 2, 0))
        labels["time"].append(600.0 * k + np.arange(n_rows))
        contacts.append(np.tile(tip if indenter == "sphere" else proximal, (n_rows, 1)))
    table = SampleTable({k: np.concatenate(v) for k, v in labels.items()})
    contact = np.concatenate(contacts)
    table.labels.update({f"contact_{a}": contact[:, i] for i, a in enumerate("xyz")})
    n = len(table)
    rng = np.random.default_rng(0)
    lab = table.labels
    residual = {
        "force_x": np.array([INDENTER_FORCE_X[i] for i in lab["indenter"]]),
        "force_y": np.array([SENSOR_FORCE_Y[s] for s in lab["sensor"]]),
        "force_z": FORCE_Z_PER_DEPTH * lab["depth"],
        "pdc": np.where(lab["normal"], 0.0, ANGLED_PDC),
        **{f"electrode_{e}": np.full(n, float(e)) for e in range(1, 20)},
    }
    for channel, r in residual.items():
        table.measured[channel] = rng.normal(size=n)
        table.predicted[channel] = table.measured[channel] - r
    failed = np.zeros(n, dtype=bool)
    failed[-NOT_CONVERGED:] = True
    for channel in residual:
        table.predicted[channel][failed] = np.nan
    lab["converged"] = ~failed
    return table


def _fullrate() -> SampleTable:
    """Two trajectories at 100 Hz: 0.1 s moves (loading, then unloading) and 0.5 s pauses."""
    per_increment = np.r_[np.zeros(10, int), np.ones(50, int)]  # move, pause
    phase = np.r_[np.tile(np.where(per_increment == 0, 0, 1), 5), np.tile(np.where(per_increment == 0, 2, 1), 5)]
    n = len(phase)
    labels = {
        "sensor": np.repeat([1, 2], n),
        "trajectory": np.repeat([0, 4], n),
        "indenter": np.full(2 * n, "sphere", dtype=object),
        "normal": np.full(2 * n, True),
        "depth": np.zeros(2 * n),
        "phase": np.tile(phase, 2),
        "time": np.r_[np.arange(n), 60000 + np.arange(n)] / RATE_HZ,
        "time_in_increment": np.tile(np.arange(n) % 60, 2) / RATE_HZ,
        "converged": np.full(2 * n, True),
    }
    rng = np.random.default_rng(1)
    table = SampleTable(labels)
    for channel in ("force_x", "force_y", "force_z"):
        table.measured[channel] = rng.normal(size=2 * n)
        planted = np.array(PHASE_FORCE_X)[labels["phase"]] if channel == "force_x" else 0.0
        table.predicted[channel] = table.measured[channel] - planted
    return table


@pytest.fixture(scope="module")
def planted() -> Comparison:
    tip, proximal = _skin_points()
    return Comparison(TwinModel(mesh_max_edge=MESH), ["a.hdf5", "b.hdf5"], _rows(tip, proximal), _fullrate(), NOISE, {})


@pytest.fixture(scope="module")
def report(planted: Comparison, tmp_path_factory: pytest.TempPathFactory) -> ReportFiles:
    return write_report(planted, tmp_path_factory.mktemp("report"), title="planted <residuals>")


@pytest.fixture(scope="module")
def summary(report: ReportFiles) -> dict:
    return json.loads(report.summary.read_text())


def test_summary_has_the_documented_shape(summary: dict, planted: Comparison) -> None:
    assert set(summary) == {
        "schema",
        "title",
        "model",
        "datasets",
        "units",
        "samples",
        "noise",
        "overall",
        "by",
        "residual_field",
    }
    assert summary["schema"] == 1 and summary["title"] == "planted <residuals>"
    assert summary["datasets"] == ["a.hdf5", "b.hdf5"]
    assert summary["model"]["key"] == planted.model.key()
    assert TwinModel.from_dict(summary["model"]) == planted.model
    assert set(summary["by"]) == {"indenter", "sensor", "normal", "depth_mm", "phase"}
    assert set(summary["by"]["indenter"]) == {"force_x", "force_y", "force_z", "force", "pdc", "electrodes"}
    assert set(summary["by"]["phase"]) == {"force_x", "force_y", "force_z", "force"}
    assert set(summary["overall"]) >= {"force", "electrodes", "pdc", *(f"electrode_{e}" for e in range(1, 20))}
    assert summary["samples"] == {
        "trajectories": 2,  # trajectories are counted in the full-rate table
        "trajectories_not_converged": 0,
        "rows": 8 * len(DEPTHS),
        "rows_converged": 8 * len(DEPTHS) - NOT_CONVERGED,
        "fullrate": 1200,
        "fullrate_converged": 1200,
    }


def test_planted_residuals_appear_in_their_groups(summary: dict) -> None:
    by = summary["by"]
    n_group = 4 * len(DEPTHS)  # rows per indenter / sensor / normal-or-angled
    for indenter, value in INDENTER_FORCE_X.items():
        stats = by["indenter"]["force_x"][indenter]
        assert stats["rms"] == pytest.approx(abs(value)) and stats["mean"] == pytest.approx(value)
    assert by["indenter"]["force_x"]["sphere"]["n"] == n_group
    assert by["indenter"]["force_x"]["cube"]["n"] == n_group - NOT_CONVERGED  # the failed trajectory is a cube's
    for sensor, value in SENSOR_FORCE_Y.items():
        assert by["sensor"]["force_y"][str(sensor)]["rms"] == pytest.approx(value, abs=1e-12)
    assert by["normal"]["pdc"]["angled"]["rms"] == pytest.approx(ANGLED_PDC)
    assert by["normal"]["pdc"]["normal"]["rms"] == pytest.approx(0.0, abs=1e-12)
    assert by["sensor"]["electrodes"]["1"]["rms"] == pytest.approx(np.sqrt(np.mean(np.arange(1, 20) ** 2)))


def test_depth_breakdown_matches_the_planted_depth_law(summary: dict) -> None:
    table = summary["by"]["depth_mm"]["force_z"]
    assert list(table) == ["<=0", "0-0.2", "0.2-0.4", "0.4-0.6", "0.6-0.8", "0.8-1"]
    depth_mm = np.round(DEPTHS * 1e3, 9)
    for name, lo, hi in (("0-0.2", 0.0, 0.2), ("0.4-0.6", 0.4, 0.6), ("0.8-1", 0.8, 1.0)):
        inside = depth_mm[(depth_mm > lo) & (depth_mm <= hi)]
        assert table[name]["rms"] == pytest.approx(np.sqrt(np.mean((FORCE_Z_PER_DEPTH * inside * 1e-3) ** 2)))
    assert table["<=0"]["rms"] == pytest.approx(0.0, abs=1e-12)


def test_phase_breakdown_uses_the_full_rate_table(summary: dict) -> None:
    table = summary["by"]["phase"]["force_x"]
    assert list(table) == list(PHASES)
    for name, value in zip(PHASES, PHASE_FORCE_X, strict=True):
        assert table[name]["mean"] == pytest.approx(value)
    assert table["pause"]["n"] == 1000 and table["loading"]["n"] == table["unloading"]["n"] == 100


def test_force_is_the_norm_of_the_per_axis_residuals(summary: dict) -> None:
    overall = summary["overall"]
    per_axis = sum(overall[c]["rms"] ** 2 for c in ("force_x", "force_y", "force_z"))
    assert overall["force"]["rms"] == pytest.approx(np.sqrt(per_axis))


def test_rows_noise_is_the_filtered_full_rate_noise(summary: dict) -> None:
    white = np.random.default_rng(2).normal(size=200_000)
    assert filtered_noise_gain(RATE_HZ) == pytest.approx(np.std(lowpass(white, RATE_HZ)), rel=0.02)
    gain = filtered_noise_gain(RATE_HZ)
    assert 0.1 < gain < 0.5
    assert summary["noise"]["force_x"] == {"fullrate": NOISE["force_x"], "rows": pytest.approx(NOISE["force_x"] * gain)}
    assert summary["noise"]["pdc"] == {"fullrate": NOISE["pdc"], "rows": NOISE["pdc"]}  # pdc rows are not filtered


def test_depth_bins() -> None:
    assert [depth_step_mm(d) for d in (0.0, 1e-3, 3e-3, 10e-3)] == [0.1, 0.2, 0.5, 2.0]
    index, name = depth_bins(np.array([0.0, 0.1e-3, 0.2e-3, 0.3e-3, 1.0e-3, -1e-3]))
    assert [name(k) for k in index] == ["<=0", "0-0.2", "0-0.2", "0.2-0.4", "0.8-1", "<=0"]


def test_figures_decode_and_are_inlined_in_the_html(report: ReportFiles) -> None:
    assert set(report.figures) == {name for name, _, _ in FIGURES}
    for path in report.figures.values():
        image = imread(path)
        assert image.ndim == 3 and min(image.shape[:2]) > 200 and image.std() > 0.01
    page = report.html.read_text()
    inlined = re.findall(r'src="data:image/png;base64,([^"]+)"', page)
    assert len(inlined) == len(FIGURES)
    assert all(imread(io.BytesIO(base64.b64decode(data))).ndim == 3 for data in inlined)
    assert "planted &lt;residuals&gt;" in page and "<residuals>" not in page
    assert "<h2>By indenter (rows)</h2>" in page and "<h2>By phase (full rate)</h2>" in page


def test_residual_field_file_puts_each_place_s_error_on_its_vertex(report: ReportFiles, summary: dict) -> None:
    field = np.load(report.residual_field)
    skin = make_biotac(MESH).skin
    np.testing.assert_array_equal(field["vertices"], skin.vertices)
    np.testing.assert_array_equal(field["triangles"], skin.triangles)
    assert field["values"].shape == field["support"].shape == (len(skin.vertices),)
    tip, proximal = _skin_points()
    at = {
        name: int(np.argmin(np.linalg.norm(skin.vertices - p, axis=1)))
        for name, p in (("sphere", tip), ("cube", proximal))
    }
    for indenter, vertex in at.items():  # the two places are out of each other's kernel reach
        assert field["values"][vertex] == pytest.approx(summary["by"]["indenter"]["force"][indenter]["rms"])
    far = np.min([np.linalg.norm(skin.vertices - skin.vertices[v], axis=1) for v in at.values()], axis=0)
    assert np.isnan(field["values"][far > KERNEL_REACH * float(field["bandwidth"])]).all()
    assert summary["residual_field"]["vertices_with_data"] == int(np.isfinite(field["values"]).sum())


def test_residual_field_peaks_at_a_planted_residual() -> None:
    skin = make_biotac(MESH).skin
    ventral = np.flatnonzero(skin.ventral)
    planted = ventral[len(ventral) // 2]
    points = np.r_[skin.vertices[ventral], skin.vertices[[planted]] + 1e-4]
    residual = np.r_[np.zeros(len(ventral)), 1.0]
    field = residual_field(skin.vertices, skin.triangles, points, residual, bandwidth=1.5e-3)
    assert np.nanargmax(field.values) == planted
    distance = np.linalg.norm(skin.vertices - skin.vertices[planted], axis=1)
    reach = distance <= KERNEL_REACH * 1.5e-3
    assert (field.values[reach] > 0).all()
    assert np.all(field.values[~reach & np.isfinite(field.values)] == 0.0)
    alone = residual_field(skin.vertices, skin.triangles, points[-1:], np.array([2.0]), bandwidth=1.5e-3)
    np.testing.assert_allclose(alone.values[reach], 2.0)  # one sample: its own magnitude wherever it reaches
    assert np.isnan(alone.values[~reach]).all()


def test_load_model_reads_a_model_json(tmp_path: Path) -> None:
    model = TwinModel(mesh_max_edge=1e-3)
    model = replace(model, skin=replace(model.skin, mu_nh=3.1e5))
    path = tmp_path / "model.json"
    path.write_text(json.dumps(model.to_dict()))
    assert model_or_nominal(path, 2e-3) == model
    assert model_or_nominal(None, 2e-3) == TwinModel(mesh_max_edge=2e-3)


def test_compare_rejects_bad_datasets(tmp_path: Path) -> None:
    missing = runner.invoke(app, ["compare", str(tmp_path / "none.hdf5"), "--out", str(tmp_path / "r")])
    assert missing.exit_code == 2 and "no such dataset" in missing.output
    dataset = tmp_path / "data.hdf5"
    dataset.write_text("not hdf5")
    result = runner.invoke(app, ["compare", str(dataset), "--out", str(tmp_path / "r")])
    assert result.exit_code == 2 and "not an HDF5 file" in result.output


@pytest.fixture(scope="module")
def tiny_campaign(tmp_path_factory: pytest.TempPathFactory, make_tiny_campaign) -> Path:
    return make_tiny_campaign(tmp_path_factory.mktemp("tiny"))


def test_compare_cli_on_a_tiny_campaign(tiny_campaign: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    result = runner.invoke(app, ["compare", str(tiny_campaign), "--out", str(out), "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary == json.loads((out / "summary.json").read_text())
    assert summary["datasets"] == [str(tiny_campaign)]
    assert summary["model"]["mesh_max_edge"] == MESH and summary["model"]["effects"] == {}
    assert summary["samples"]["trajectories"] == 2 and summary["samples"]["trajectories_not_converged"] == 0
    assert set(summary["by"]["normal"]["force"]) == {"normal", "angled"}
    assert set(summary["by"]["indenter"]["force"]) == {"sphere_medium"}
    force = summary["overall"]["force"]
    assert force["n"] == summary["samples"]["rows"] and 0.0 < force["rms"] < 0.5  # the plant is not the model
    assert 0.0 < summary["noise"]["force_z"]["fullrate"] < 0.1
    assert summary["residual_field"]["vertices_with_data"] > 0
    assert (out / "report.html").stat().st_size > 10_000 and (out / "residual_field.npz").exists()


def test_compare_cli_rejects_a_bad_model(tiny_campaign: Path, tmp_path: Path) -> None:
    model = tmp_path / "model.json"
    model.write_text('{"effects": {}}')
    result = runner.invoke(app, ["compare", str(tiny_campaign), "--model", str(model), "--out", str(tmp_path)])
    assert result.exit_code == 2 and "not a model JSON" in result.output
