"""Rerun views: `twin view` on datasets (stored and FE-replayed displacement) and reports, the env's live
logging and the campaign viewer, each checked by reading the saved .rrd back with rerun's own reader."""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path

import h5py
import numpy as np
import pytest
from rerun.chunk import RrdReader
from typer.testing import CliRunner

from assets.biotac import electrode_table
from assets.indenters import INDENTERS, get_indenter
from twin.analysis.report.field import residual_field
from twin.cli import app
from twin.envs.press import PressEnv
from twin.fe_models import shared_model
from twin.view import CampaignViewer, open_recording
from twin.view.scene import FORCE_ARROW_M_PER_N, NAN_COLOUR

runner = CliRunner()
DEPTHS = np.array([0.0, 0.25, 0.5, 0.75, 1.0]) * 1e-3  # m, one trajectory's rows
POINT = np.array([-6e-3, 0.0, -9e-3])
SCENE = {"skin", "indenter", "indenter/shape", "force", "electrodes"}
SERIES = {"force", "electrodes", "pressure", "pdc"}


def _entities(path: Path) -> dict[str, dict[str, list]]:
    """entity path -> component column -> values of every logged row, ordered by the first timeline
    that orders them (`row` or `step`; static rows first)."""
    rows: dict[str, list[tuple[int, dict]]] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = {n: batch.column(n).to_pylist() for n in batch.schema.names if ":" in n}
        order = next((batch.column(t).to_pylist() for t in ("row", "step") if t in batch.schema.names), None)
        for i in range(batch.num_rows):
            key = -1 if order is None or order[i] is None else int(order[i])
            rows[chunk.entity_path.lstrip("/")].append((key, {n: v[i] for n, v in columns.items()}))
    out: dict[str, dict[str, list]] = {}
    for entity, items in rows.items():
        merged: dict[str, list] = defaultdict(list)
        for _, values in sorted(items, key=lambda item: item[0]):
            for name, value in values.items():
                if value is not None:
                    merged[name].append(value)
        out[entity] = dict(merged)
    return out


def _chunks(path: Path, entity: str) -> list[tuple[bool, dict[str, list]]]:
    """(static?, column name -> values) of every chunk of `entity` in the recording at `path`: components,
    `row`, `time` in s; other timelines (log_tick, log_time) by name only (None)."""
    out = []
    for chunk in RrdReader(path).stream():
        if chunk.entity_path.lstrip("/") == entity:
            batch = chunk.to_record_batch()
            columns: dict[str, list | None] = {n: None for n in batch.schema.names}
            columns |= {n: batch.column(n).to_pylist() for n in columns if ":" in n or n == "row"}
            if "time" in columns:
                columns["time"] = (np.array(batch.column("time").cast("int64").to_pylist()) * 1e-9).tolist()
            out.append((chunk.is_static, columns))
    return out


def _temporal(path: Path, entity: str, component: str) -> tuple[np.ndarray, list]:
    """`row` indices and values of `component` over the temporal chunks of `entity`, ordered by row."""
    rows, values = [], []
    for static, columns in _chunks(path, entity):
        if not static and component in columns:
            rows += columns["row"]
            values += columns[component]
    order = np.argsort(rows, kind="stable")
    return np.array(rows)[order], [values[i] for i in order]


def _layouts(path: Path) -> list[tuple[set[tuple[str, str, str]], list[int]]]:
    """The recording's blueprints (`_layout` of each)."""
    reader = RrdReader(path)
    assert reader.blueprints(), f"{path} carries no blueprint"
    return [_layout(reader, store) for store in reader.blueprints()]


def _layout(reader: RrdReader, store) -> tuple[set[tuple[str, str, str]], list[int]]:
    """A blueprint: its views as (class, origin, contents query) and the kinds of its containers (rerun's
    ContainerKind: 1 tabs, 2 horizontal, 3 vertical, 4 grid), root first."""
    fields: dict[str, dict[str, object]] = defaultdict(dict)
    for chunk in reader.stream(store=store):
        batch = chunk.to_record_batch()
        for name in batch.schema.names:
            if ":" in name:
                fields[chunk.entity_path.strip("/")][name] = np.ravel(batch.column(name).to_pylist()[-1]).tolist()
    views = {
        (f["ViewBlueprint:class_identifier"][0], f["ViewBlueprint:space_origin"][0], query)
        for path_, f in fields.items()
        if "ViewBlueprint:class_identifier" in f
        for query in fields[f"{path_}/ViewContents"]["ViewContents:query"]
    }
    containers = {p: f for p, f in fields.items() if "ContainerBlueprint:container_kind" in f}
    children = {c for f in containers.values() for c in f.get("ContainerBlueprint:contents", [])}
    roots = [p for p in containers if p not in children]
    assert len(roots) == 1
    kinds = [containers[roots[0]]["ContainerBlueprint:container_kind"][0]]
    kinds += [f["ContainerBlueprint:container_kind"][0] for p, f in containers.items() if p != roots[0]]
    return views, kinds


def _packed(rgba: np.ndarray) -> int:
    r, g, b, a = (int(c) for c in rgba)
    return (r << 24) | (g << 16) | (b << 8) | a


def _trajectory(model) -> dict[str, np.ndarray]:
    """A trajectory's rows along the planned normal path at POINT (sphere_medium), synthetic sensor values."""
    path = model.plan_trajectory(get_indenter("sphere_medium"), POINT, 0.0, 0.0, 0.0, 1.0)
    n = len(DEPTHS)
    tip = path.touch_point + np.outer(DEPTHS, path.direction)
    near = np.exp(-np.sum((model.reference - path.touch_point) ** 2, axis=1) / (2e-3) ** 2)
    return {
        "rotation": path.rotation,
        "touch_point": path.touch_point,
        "direction": path.direction,
        "depth": DEPTHS,
        "contact_loc": tip,
        "time": 0.5 * np.arange(n),
        "force": np.outer(DEPTHS * 2e3, [0.0, 0.0, 1.0]),
        "electrode_vals": -np.outer(DEPTHS * 2e5, np.linspace(0.5, 1.0, 19)),
        "pdc": 1500.0 + DEPTHS * 1e5,
        "fe_pressure": 38e3 + DEPTHS * 4e6,
        "nodal_res": (DEPTHS[:, None, None] * near[None, :, None] * path.direction).astype(np.float32),
    }


def _write_dataset(
    path: Path, model, trajectory_ids: list[int], stored: bool, indenters: tuple[str, ...] = ("sphere_medium",)
) -> dict[str, np.ndarray]:
    """A schema-v1 file (docs/dataset.md) of trajectories with identical rows, the i-th labelled with
    indenters[i % len(indenters)]; `stored`: with nodal_res and mesh."""
    rows = _trajectory(model)
    n = len(DEPTHS)
    features = ("depth", "contact_loc", "time", "force", "electrode_vals", "pdc", "fe_pressure")
    features += ("nodal_res",) if stored else ()
    with h5py.File(path, "w") as f:
        f.attrs.update(schema_version=1, sensor_id=1, indenter_names=json.dumps(list(INDENTERS)))
        f.attrs["provenance"] = json.dumps({"config": {"mesh_max_edge": 2e-3}})
        for name in features:
            f.create_dataset(f"{name}/data", data=np.concatenate([rows[name]] * len(trajectory_ids)))
        meta = {
            "trajectory_id": trajectory_ids,
            "indenter_type": [list(INDENTERS).index(indenters[k % len(indenters)]) for k in range(len(trajectory_ids))],
            "first_row": [k * n for k in range(len(trajectory_ids))],
            "n_rows": [n] * len(trajectory_ids),
        }
        meta |= {k: [rows[k]] * len(trajectory_ids) for k in ("rotation", "touch_point", "direction")}
        for name, values in meta.items():
            f.create_dataset(f"trajectories/{name}", data=np.array(values))
        if stored:
            f.create_dataset("mesh/vertices", data=model.reference)
            f.create_dataset("mesh/triangles", data=model.geometry.skin.triangles)
    return rows


@pytest.fixture(scope="module")
def model():
    return shared_model(2.0)


def test_view_dataset_logs_every_field_of_the_chosen_trajectory(model, tmp_path: Path) -> None:
    rows = _write_dataset(tmp_path / "stored.hdf5", model, [4, 9], stored=True, indenters=("cube", "sphere_medium"))
    out = tmp_path / "view.rrd"
    result = runner.invoke(app, ["view", str(tmp_path / "stored.hdf5"), "--save", str(out), "--trajectory", "9"])
    assert result.exit_code == 0, result.output
    logged = _entities(out)
    assert {f"biotac/{e}" for e in SCENE} | {f"series/biotac/{s}" for s in SERIES} <= set(logged)
    n, v = len(DEPTHS), len(model.reference)
    skin = logged["biotac/skin"]
    assert len(skin["Mesh3D:vertex_positions"]) == n  # one trajectory's rows, not both
    for k in range(n):
        positions = np.array(skin["Mesh3D:vertex_positions"][k])
        assert positions.shape == (v, 3)
        assert np.allclose(positions, model.reference + rows["nodal_res"][k], atol=1e-7)
    assert len(set(skin["Mesh3D:vertex_colors"][0])) == 1 < len(set(skin["Mesh3D:vertex_colors"][-1]))
    indenter = logged["biotac/indenter"]
    translations = np.array(indenter["Transform3D:translation"]).reshape(-1, 3)
    assert np.allclose(translations, rows["contact_loc"], atol=1e-7)
    matrix = np.array(indenter["Transform3D:mat3x3"][0]).reshape(3, 3).T  # stored column-major
    assert np.allclose(matrix, rows["rotation"], atol=1e-6)
    arrows = np.array(logged["biotac/force"]["Arrows3D:vectors"]).reshape(-1, 3)
    assert np.allclose(arrows, rows["force"] * FORCE_ARROW_M_PER_N, atol=1e-7)
    electrodes = logged["biotac/electrodes"]
    assert np.array(electrodes["Points3D:positions"][0]) == pytest.approx(electrode_table().positions, abs=1e-7)
    assert np.array(logged["series/biotac/electrodes"]["Scalars:scalars"]).shape == (n, 19)
    assert np.allclose(logged["series/biotac/force"]["Scalars:scalars"], rows["force"])
    assert np.allclose(np.ravel(logged["series/biotac/pressure"]["Scalars:scalars"]), rows["fe_pressure"])
    shape = logged["biotac/indenter/shape"]["Mesh3D:vertex_positions"]
    assert len(shape) == 1 and len(shape[0]) == len(get_indenter("sphere_medium").mesh(1e-3).vertices)


def test_view_logs_the_topology_once_and_each_trajectory_as_whole_columns(model, tmp_path: Path) -> None:
    """Triangles, electrode positions and the arrow colour are static and sent once; positions and colours
    come per row, each trajectory's rows as columns (rr.send_columns: only the `row` and `time` timelines,
    no log_tick) equal to the file's arrays; the default layout travels with the file."""
    rows = _write_dataset(tmp_path / "two.hdf5", model, [4, 9], stored=True)
    out = tmp_path / "two.rrd"
    args = ["view", str(tmp_path / "two.hdf5"), "--save", str(out), "--trajectory", "4", "--trajectory", "9"]
    assert runner.invoke(app, args).exit_code == 0
    n, triangles = len(DEPTHS), model.geometry.skin.triangles
    skin = _chunks(out, "biotac/skin")
    topology = [columns["Mesh3D:triangle_indices"] for static, columns in skin if "Mesh3D:triangle_indices" in columns]
    assert len(topology) == 1 and all(static for static, columns in skin if "Mesh3D:triangle_indices" in columns)
    assert np.array_equal(np.array(topology[0][0]), triangles)
    for entity in ("biotac/skin", "biotac/indenter", "biotac/force", "biotac/electrodes", "series/biotac/force"):
        timelines = {k for static, c in _chunks(out, entity) if not static for k in c if ":" not in k}
        assert timelines == {"rerun.controls.RowId", "row", "time"}, (entity, timelines)
    row, positions = _temporal(out, "biotac/skin", "Mesh3D:vertex_positions")
    assert row.tolist() == list(range(2 * n))
    expected = model.reference + np.concatenate([rows["nodal_res"]] * 2)
    assert np.allclose(np.array(positions), expected, atol=1e-7)
    assert len(_temporal(out, "biotac/skin", "Mesh3D:vertex_colors")[1]) == 2 * n
    times = [t for static, c in _chunks(out, "biotac/skin") if not static for t in c["time"]]
    assert sorted(times) == sorted(np.concatenate([rows["time"]] * 2).tolist())
    electrodes = _chunks(out, "biotac/electrodes")
    assert [static for static, c in electrodes if "Points3D:positions" in c] == [True]
    assert len(_temporal(out, "biotac/electrodes", "Points3D:colors")[1]) == 2 * n
    for series, name in (("force", "force"), ("electrodes", "electrode_vals"), ("pressure", "fe_pressure")):
        logged = np.array(_temporal(out, f"series/biotac/{series}", "Scalars:scalars")[1]).reshape(2 * n, -1)
        assert np.allclose(logged, np.concatenate([rows[name]] * 2).reshape(2 * n, -1)), series
    logged = np.ravel(_temporal(out, "series/biotac/pdc", "Scalars:scalars")[1])
    assert np.allclose(logged, np.concatenate([rows["pdc"]] * 2))
    [(views, kinds)] = _layouts(out)
    assert kinds[0] == 2  # side by side
    assert {("3D", "/biotac", "$origin/**"), ("3D", "/report", "$origin/**")} <= views
    assert {("TimeSeries", "/series", f"/series/biotac/{s}") for s in SERIES} <= views


def test_view_dataset_draws_each_trajectorys_indenter_in_turn(model, tmp_path: Path) -> None:
    _write_dataset(tmp_path / "two.hdf5", model, [4, 9], stored=True, indenters=("cube", "sphere_medium"))
    out = tmp_path / "two.rrd"
    args = ["view", str(tmp_path / "two.hdf5"), "--save", str(out), "--trajectory", "4", "--trajectory", "9"]
    assert runner.invoke(app, args).exit_code == 0
    logged = _entities(out)
    assert len(logged["biotac/skin"]["Mesh3D:vertex_positions"]) == 2 * len(DEPTHS)
    shapes = logged["biotac/indenter/shape"]["Mesh3D:vertex_positions"]  # cube first, then the sphere
    expected = [len(get_indenter(name).mesh(1e-3).vertices) for name in ("cube", "sphere_medium")]
    assert [len(s) for s in shapes] == expected and expected[0] != expected[1]


def test_view_replays_the_fe_when_the_dataset_has_no_displacement(model, tmp_path: Path) -> None:
    rows = _write_dataset(tmp_path / "bare.hdf5", model, [0], stored=False)
    out = tmp_path / "replay.rrd"
    result = runner.invoke(app, ["view", str(tmp_path / "bare.hdf5"), "--save", str(out)])
    assert result.exit_code == 0, result.output
    positions = np.array(_entities(out)["biotac/skin"]["Mesh3D:vertex_positions"])
    assert positions.shape == (len(DEPTHS), len(model.reference), 3)
    moved = np.linalg.norm(positions - model.reference, axis=2)
    assert moved[0].max() < 1e-6  # first touch: undeformed
    assert np.all(np.diff(moved.max(axis=1)) > 0) and 0.5e-3 < moved[-1].max() < 1.2e-3  # ~1 mm press
    deepest = model.reference[np.argmax(moved[-1])]
    assert np.linalg.norm(deepest - rows["touch_point"]) < 4e-3  # the dent is under the indenter


def test_view_report_logs_the_residual_field_on_the_skin(model, tmp_path: Path) -> None:
    vertices, triangles = model.geometry.skin.vertices, model.geometry.skin.triangles
    points = np.array([POINT, POINT + [5e-3, 0.0, 0.0]])  # on different vertices of the 2 mm mesh
    field = residual_field(vertices, triangles, points, np.array([0.1, 0.5]), 2e-3)
    report = tmp_path / "report"
    report.mkdir()
    field.save(report / "residual_field.npz")
    overall = {"force": {"rms": 0.32, "mean": 0.3, "n": 2}}
    (report / "summary.json").write_text(json.dumps({"overall": overall}))
    out = tmp_path / "report.rrd"
    result = runner.invoke(app, ["view", str(report), "--save", str(out)])
    assert result.exit_code == 0, result.output
    logged = _entities(out)
    mesh = logged["report/residual_field"]
    assert np.allclose(mesh["Mesh3D:vertex_positions"][0], vertices)
    colours = np.array(mesh["Mesh3D:vertex_colors"][0])
    unknown = ~np.isfinite(field.values)
    assert unknown.any() and np.all(colours[unknown] == _packed(NAN_COLOUR))
    assert len(set(colours[~unknown])) > 3
    assert "| force | 0.32 | 0.3 | 2 |" in np.ravel(logged["report/summary"]["TextDocument:text"])[0]
    [(views, _)] = _layouts(out)  # the field opens in the same layout as the datasets
    assert {("3D", "/report", "$origin/**"), ("3D", "/biotac", "$origin/**")} <= views


def test_env_logs_every_step_live(tmp_path: Path) -> None:
    out = tmp_path / "env.rrd"
    env = PressEnv(render_mode="rerun", rerun_save=out, max_steps=3, standoff_mm=(0.3, 0.3), start_offset_mm=0.0)
    env.reset(seed=2)
    forces = [env.step(np.array([0.0, 0.0, 1.0]))[4]["force_n"] for _ in range(3)]
    env.close()
    logged = _entities(out)
    assert len(logged["biotac/skin"]["Mesh3D:vertex_positions"]) == 4  # reset + 3 steps
    arrows = np.array(logged["biotac/force"]["Arrows3D:vectors"]).reshape(-1, 3)
    assert np.allclose(arrows[1:], np.array(forces) * FORCE_ARROW_M_PER_N, atol=1e-7)
    assert np.array(logged["series/biotac/electrodes"]["Scalars:scalars"]).shape == (4, 19)
    assert len(logged["biotac/indenter/shape"]["Mesh3D:triangle_indices"]) == 1
    topology = [static for static, c in _chunks(out, "biotac/skin") if "Mesh3D:triangle_indices" in c]
    assert topology == [True]  # sent once, not with each step
    assert ("3D", "/biotac", "$origin/**") in _layouts(out)[0][0]


def test_campaign_viewer_logs_finished_trajectories_in_turn(model, tmp_path: Path) -> None:
    rows = _trajectory(model)
    arrays = {f"row_{k}": v for k, v in rows.items() if k not in ("rotation", "touch_point", "direction")}
    arrays |= {"meta_rotation": rows["rotation"], "meta_indenter_type": np.array(1), "mesh_reference": model.reference}
    out = tmp_path / "campaign.rrd"
    recording = open_recording("campaign-test", save=out)
    viewer = CampaignViewer(recording, model.geometry.skin.triangles)
    viewer.log_trajectory(2, arrays)
    viewer.log_trajectory(2, arrays)
    viewer.log_trajectory(5, arrays)
    viewer.close()
    logged = _entities(out)
    assert len(logged["biotac2/skin"]["Mesh3D:vertex_positions"]) == 2 * len(DEPTHS)
    assert np.array(logged["series/biotac2/force"]["Scalars:scalars"]).shape == (2 * len(DEPTHS), 3)
    skins = {("3D", "/biotac2", "$origin/**"), ("3D", "/biotac5", "$origin/**")}
    tabbed = [views for views, kinds in _layouts(out) if skins <= views and 1 in kinds]  # re-sent: a tab per sensor
    assert len(tabbed) == 1 and ("TimeSeries", "/series", "/series/biotac5/force") in tabbed[0]
    with pytest.raises(ValueError, match="row_nodal_res"):
        viewer.log_trajectory(2, {k: v for k, v in arrays.items() if k != "row_nodal_res"})


def test_view_refuses_bad_input_with_a_clear_message(model, tmp_path: Path) -> None:
    _write_dataset(tmp_path / "d.hdf5", model, [3], stored=True)
    cases = [
        ([str(tmp_path / "d.hdf5"), "--save", str(tmp_path / "x.txt")], ".rrd"),
        ([str(tmp_path / "d.hdf5"), "--save", str(tmp_path / "x.rrd"), "--trajectory", "5"], "no trajectory [5]"),
        ([str(tmp_path), "--save", str(tmp_path / "y.rrd")], "not a `twin compare` report"),
    ]
    for args, message in cases:
        result = runner.invoke(app, ["view", *args])
        assert result.exit_code == 2 and message in " ".join(result.output.split()), result.output


def test_campaign_run_records_each_trajectory_live(tmp_path: Path) -> None:
    rrd = tmp_path / "live.rrd"
    args = ["campaign", "run", "--quick", "--sensors", "2", "--indenters", "sphere_medium", "--workers", "1"]
    result = CliRunner().invoke(app, [*args, "--out", str(tmp_path / "c"), "--view-save", str(rrd)])
    assert result.exit_code == 0, result.output
    entities = _entities(rrd)
    assert {"biotac2/force", "biotac2/electrodes", "biotac2/indenter"} <= set(entities), sorted(entities)[:20]
