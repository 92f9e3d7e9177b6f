"""Learning happens on a tiny synthetic campaign: losses fall, models beat the mean predictor; checkpoints,
fine-tuning, cross-sensor evaluation and the CLI work. Not exact numbers."""

import json
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from typer.testing import CliRunner

from learn.checkpoint import Checkpoint
from learn.data import load
from learn.experiment import SplitSpec, evaluate_checkpoint, train
from learn.metrics import paper_metrics
from learn.splits import split
from learn.synthetic import write_synthetic_campaign
from learn.train import NeuralEstimator, TrainConfig
from twin.cli.learn import learn_app

torch.set_num_threads(1)
FAST = TrainConfig(max_epochs=30, batch_size=32, threads=1, patience=30)


@pytest.fixture(scope="module")
def sensors(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("campaign")
    a = write_synthetic_campaign(folder / "biotac1.hdf5", 40, sensor_id=1, seed=11)
    b = write_synthetic_campaign(folder / "biotac2.hdf5", 12, sensor_id=2, seed=12)
    return a, b


@pytest.fixture(scope="module")
def mean_metrics(sensors: tuple[Path, Path]) -> dict:
    return train([sensors[0]], "mean").metrics["combined"]


def test_mlp_learns_every_target_and_beats_the_mean(sensors: tuple[Path, Path], mean_metrics: dict) -> None:
    ckpt = train([sensors[0]], "mlp", SplitSpec("contiguous"), FAST)
    history = ckpt.estimator.history
    assert history[-1].train_loss < 0.5 * history[0].train_loss
    got = ckpt.metrics["combined"]
    assert got["contact_loc_mean_mm"] < 0.8 * mean_metrics["contact_loc_mean_mm"]
    assert got["force_magnitude_median_N"] < mean_metrics["force_magnitude_median_N"]
    assert got["force_angle_mean_rad"] < mean_metrics["force_angle_mean_rad"]
    assert got["nodal_mean_mm"] < mean_metrics["nodal_mean_mm"]


def test_pointnet_learns_contact_location(sensors: tuple[Path, Path]) -> None:
    """Twenty epochs on ~30 trajectories: the fit is clear on the training rows; on unseen trajectories it
    still beats the mean. Over seeds 0-4 (2026-11-29, this 2-core box) the training error was 0.32-0.62 and the test
    error 0.45-0.85 of the mean predictor's; ten epochs were too few on this machine's arithmetic (seed 0: 0.87 and
    1.05)."""
    data = load(sensors[0])
    train_rows, test_rows = split(data, "contiguous", 0.2, seed=0)
    training, test = data.subset(train_rows), data.subset(test_rows)
    config = TrainConfig(targets=("contact_loc",), max_epochs=20, batch_size=32, learning_rate=2e-3, threads=1)
    estimator = NeuralEstimator(config).fit(training)
    assert estimator.history[-1].train_loss < 0.5 * estimator.history[0].train_loss
    mean = training.contact_loc.mean(axis=0)

    def error_ratio(part) -> float:
        floor = paper_metrics({"contact_loc": np.tile(mean, (len(part), 1))}, part.targets())
        return (
            paper_metrics(estimator.predict(part), part.targets())["contact_loc_mean_mm"] / floor["contact_loc_mean_mm"]
        )

    assert error_ratio(training) < 0.75
    assert error_ratio(test) < 1.0


def test_classical_baselines_beat_the_mean(sensors: tuple[Path, Path], mean_metrics: dict) -> None:
    got = train([sensors[0]], "classical").metrics["combined"]
    assert got["contact_loc_mean_mm"] < 0.6 * mean_metrics["contact_loc_mean_mm"]
    assert got["force_magnitude_median_N"] < mean_metrics["force_magnitude_median_N"]


def test_leave_one_indenter_out_tests_only_that_indenter(sensors: tuple[Path, Path]) -> None:
    data = load(sensors[0])
    indenter = data.indenter_names[data.indenter[0]]
    held_out = train([sensors[0]], "classical", SplitSpec(f"indenter:{indenter}")).metrics["combined"]
    assert held_out["n_samples"] == np.count_nonzero(data.indenter == data.indenter[0])


def test_checkpoint_round_trip_and_data_check(sensors: tuple[Path, Path], tmp_path: Path) -> None:
    ckpt = train([sensors[0]], "mlp", SplitSpec("contiguous"), TrainConfig(max_epochs=2, threads=1))
    path = ckpt.save(tmp_path / "m.pt")
    again = Checkpoint.load(path)
    data = load(sensors[0], node_ids=np.asarray(ckpt.training["node_ids"]))
    for k, v in ckpt.estimator.predict(data).items():
        np.testing.assert_allclose(again.estimator.predict(data)[k], v)
    assert again.training["data_hashes"]["biotac1"] == data.content_hash()
    assert again.training["split"]["name"] == "contiguous" and again.metrics == ckpt.metrics
    rescored = evaluate_checkpoint(again, [sensors[0]])["combined"]
    assert rescored == pytest.approx(ckpt.metrics["combined"])
    altered = tmp_path / "biotac1.hdf5"
    altered.write_bytes(sensors[0].read_bytes())
    with h5py.File(altered, "r+") as f:
        f["electrode_vals/data"][0, 0] += 1.0
    with pytest.raises(ValueError, match="differs"):
        evaluate_checkpoint(again, [altered])
    with pytest.raises(ValueError, match="not a biotac-twin"):
        torch.save({"x": 1}, tmp_path / "other.pt")
        Checkpoint.load(tmp_path / "other.pt")


def test_pretrain_fine_tune_and_cross_sensor(sensors: tuple[Path, Path]) -> None:
    config = TrainConfig(max_epochs=3, threads=1)
    pretrained = train(list(sensors), "mlp", SplitSpec("contiguous"), config)
    assert set(pretrained.metrics["per_sensor"]) == {"biotac1", "biotac2"} and pretrained.metrics["combined"]
    tuned = train([sensors[1]], "mlp", SplitSpec("contiguous"), config, init=pretrained)
    np.testing.assert_array_equal(tuned.estimator.input_scale.low, pretrained.estimator.input_scale.low)
    assert tuned.training["fine_tuned_from"] == pretrained.training["data_hashes"]
    with pytest.raises(ValueError, match="fine-tune"):
        train([sensors[1]], "pointnet", init=pretrained)
    only_a = train([sensors[0]], "classical", SplitSpec("none"))
    unseen = evaluate_checkpoint(only_a, [sensors[1]], on="all")
    assert list(unseen["per_sensor"]) == ["biotac2"]
    assert unseen["combined"]["n_samples"] == len(load(sensors[1]))


def test_cli_train_eval_predict(sensors: tuple[Path, Path], tmp_path: Path) -> None:
    runner = CliRunner()
    ckpt = tmp_path / "cli.pt"
    args = ["train", str(sensors[0]), str(sensors[1]), "--model", "mlp", "--max-epochs", "2", "--threads", "1"]
    result = runner.invoke(learn_app, [*args, "--out", str(ckpt), "--json"])
    assert result.exit_code == 0, result.output
    result = runner.invoke(learn_app, ["eval", str(ckpt), "--json"])
    assert result.exit_code == 0, result.output
    (table,) = json.loads(result.stdout)
    assert table["model"] == "mlp" and table["split"] == "contiguous"
    assert set(table["per_sensor"]) == {"biotac1", "biotac2"}
    for key in ("contact_loc_mean_mm", "contact_loc_median_mm", "force_magnitude_median_N", "nodal_mean_mm"):
        assert np.isfinite(table["combined"][key])
    out = tmp_path / "pred.h5"
    result = runner.invoke(learn_app, ["predict", str(ckpt), str(sensors[1]), "--out", str(out)])
    assert result.exit_code == 0, result.output
    with h5py.File(out, "r") as f:
        assert f["nodal/data"].shape == (len(load(sensors[1])), 128, 3)
        assert f["force/data"].attrs["units"] == "N"
    bad = runner.invoke(learn_app, ["train", str(sensors[0]), "--split", "sideways", "--model", "mean"])
    assert bad.exit_code == 2 and "unknown split" in bad.output
