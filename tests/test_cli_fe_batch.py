"""`twin fe batch`: the results file's contract, a round trip through --poses, a --model, and bad input."""

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from fe.params import SkinParameters
from twin.analysis.predict import TwinModel
from twin.cli import app
from twin.cli import fe_batch as cli_fe_batch
from twin.fe_batch_results import BatchResults

runner = CliRunner()
COARSE = ["--mesh-mm", "2", "--device", "cpu"]


def test_batch_writes_per_pose_results_that_rerun_identically(tmp_path: Path) -> None:
    first = tmp_path / "random.npz"
    args = ["fe", "batch", "--out", str(first), "--trajectories", "3", "--indenters", "sphere_medium,cube"]
    result = runner.invoke(app, [*args, "--depth-mm", "0.4", "--slots", "2", "--json", *COARSE])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["trajectories"] == 3 and summary["ended"] == 3 and summary["not_converged"] == 0
    data = np.load(first)
    assert list(data["names"]) == ["cube", "sphere_medium", "sphere_medium"]  # indenters cycled, round robin
    assert data["force"].shape == (3, 6, 3) and data["rotations"].shape == (3, 6, 3, 3)
    assert np.all(data["poses_done"] == 6) and data["converged"].all()
    assert data["loaded"].sum() == summary["loaded_increments"] and np.all(data["contact_area"][data["loaded"]] > 0)
    magnitude = np.linalg.norm(data["force"], axis=2)
    assert np.all(np.diff(magnitude, axis=1) >= -1e-9)  # pressing deeper never pushes back less
    assert np.all(magnitude[:, -1] > 0.05)
    np.testing.assert_allclose(np.diff(data["depth"], axis=1), 1e-4, atol=1e-9)

    again = tmp_path / "again.npz"
    rerun = ["fe", "batch", "--out", str(again), "--poses", str(first), "--slots", "3", *COARSE]
    result = runner.invoke(app, rerun)
    assert result.exit_code == 0, result.output
    np.testing.assert_allclose(np.load(again)["force"], data["force"], rtol=1e-9, atol=1e-12)


def test_batch_writes_what_has_ended_while_it_runs(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With the flush period at 0 s the file is rewritten as each trajectory ends, before the final write."""
    ended: list[int] = []
    save = BatchResults.save

    def counting(self: BatchResults) -> None:
        ended.append(int(self.arrays["ended"].sum()))
        save(self)

    monkeypatch.setattr(cli_fe_batch, "FLUSH_S", 0.0)
    monkeypatch.setattr(BatchResults, "save", counting)
    out = tmp_path / "r.npz"
    args = ["fe", "batch", "--out", str(out), "--trajectories", "2", "--indenters", "cube", "--depth-mm", "0.1"]
    result = runner.invoke(app, [*args, "--slots", "1", *COARSE])
    assert result.exit_code == 0, result.output
    assert ended == [1, 2, 2] and np.all(np.load(out)["poses_done"] == 3)


def test_resume_runs_only_what_had_not_ended(tmp_path: Path) -> None:
    out = tmp_path / "r.npz"
    args = ["fe", "batch", "--out", str(out), "--trajectories", "3", "--indenters", "cube,sphere_small"]
    args += ["--depth-mm", "0.2", "--slots", "3", "--json", *COARSE]
    assert runner.invoke(app, args).exit_code == 0
    full = dict(np.load(out))
    crashed = dict(full, ended=np.array([True, False, True]), poses_done=np.array([4, 0, 4]))
    crashed["force"] = full["force"].copy()
    crashed["force"][1] = np.nan
    np.savez(out, **crashed)
    result = runner.invoke(app, [*args, "--resume"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["run_now"] == 1 and summary["ended"] == 3
    np.testing.assert_allclose(np.load(out)["force"], full["force"], rtol=1e-9, atol=1e-12)
    result = runner.invoke(app, [*args, "--resume", "--seed", "1"])
    assert result.exit_code == 2 and "holds other trajectories" in result.output
    result = runner.invoke(app, [*args, "--resume", "--force-limit", "10", "--max-cuts", "1"])  # same poses
    assert result.exit_code == 2 and "made with other force_limit_n, max_cuts" in result.output, result.output


def test_batch_rejects_bad_input_with_a_message(tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    np.savez(bad, names=np.array(["cube"]), rotations=np.zeros((1, 2, 3)), translations=np.zeros((1, 2, 3)))
    result = runner.invoke(app, ["fe", "batch", "--out", str(tmp_path / "x.npz"), "--poses", str(bad), *COARSE])
    assert result.exit_code == 2 and "rotations must be (M,K,3,3)" in result.output
    result = runner.invoke(app, ["fe", "batch", "--out", str(tmp_path / "x.npz"), "--device", "cuda:99"])
    assert result.exit_code == 2 and "'cuda:99' is not available" in result.output
    result = runner.invoke(app, ["fe", "batch", "--out", str(tmp_path / "x.npz"), "--indenters", "spoon"])
    assert result.exit_code == 2 and "unknown indenter" in result.output
    result = runner.invoke(app, ["fe", "batch", "--out", str(tmp_path / "x.npz"), "--poses", str(tmp_path / "no.npz")])
    assert result.exit_code == 2 and "no poses file" in result.output
    result = runner.invoke(app, ["fe", "batch", "--out", str(tmp_path / "x.npz"), "--max-cuts", "-1"])
    assert result.exit_code == 2 and "--max-cuts" in result.output


def test_batch_rejects_a_bad_model_with_one_line(tmp_path: Path) -> None:
    args = ["fe", "batch", "--out", str(tmp_path / "x.npz"), "--model"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"skin": {"friction": -1.0}, "mesh_max_edge": 2e-3}))
    for path, message in ((tmp_path / "no.json", "cannot read the model"), (bad, "friction=-1")):
        result = runner.invoke(app, [*args, str(path)])
        errors = [line for line in result.output.splitlines() if line.startswith("error:")]
        assert result.exit_code == 2 and len(errors) == 1 and message in errors[0], result.output


def test_batch_runs_a_model_with_relaxation_and_trapped_air(tmp_path: Path) -> None:
    skin = SkinParameters(relaxation_fraction=0.3, air_volume_fraction=0.05)
    model = tmp_path / "m.json"
    model.write_text(json.dumps(TwinModel(skin, mesh_max_edge=2e-3).to_dict()))
    out = tmp_path / "r.npz"
    args = ["fe", "batch", "--out", str(out), "--model", str(model), "--device", "cpu", "--trajectories", "2"]
    result = runner.invoke(app, [*args, "--indenters", "sphere_medium", "--depth-mm", "0.2", "--slots", "2", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout.strip().splitlines()[-1])
    assert summary["ended"] == 2 and summary["not_converged"] == 0
    assert summary["mesh_mm"] == 2.0 and summary["model"] == str(model)
    assert np.all(np.linalg.norm(np.load(out)["force"][:, -1], axis=1) > 0)
