"""Bad input to the `twin` commands ends with one `error:` line and exit code 2, never a traceback; the
`twin fe` commands refuse what they cannot solve and agree on exit codes between the table and --json."""

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from fake_campaign import write_fake_campaign
from typer.testing import CliRunner

from fe.balloon import MAX_VOLUME_RATIO, analytic_balloon_pressure, inflate_balloon
from twin.cli import app

runner = CliRunner()


def _usage_error(args: list[str], needle: str) -> None:
    """The command exits 2 with exactly one `error:` line containing `needle`, without a traceback."""
    result = runner.invoke(app, args)
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit), (result.output, result.exception)
    assert len(errors) == 1 and needle in errors[0], result.output


BALLOON = ["fe", "balloon", "--subdivisions", "1", "--volume-ratios"]


@pytest.mark.parametrize(
    ("ratios", "needle"),
    [("0.5,0.9", "compression"), ("1", "must be > 1"), ("1000", "elongation at break"), ("1.5,nan", "nan")],
)
def test_balloon_refuses_ratios_it_cannot_solve(ratios: str, needle: str) -> None:
    _usage_error([*BALLOON, ratios], needle)


def test_balloon_reaches_the_largest_ratio_in_few_steps_on_membrane_theory() -> None:
    """Stretch 5 (V/V0 = 125) in geometric steps of at most 10 % volume: ln(125) / ln(1.1) = 51 steps, and
    the pressure still within 3 % of membrane theory on a coarse icosphere."""
    steps: list[int] = []
    (point,) = inflate_balloon(
        0.01, 1e-4, 1e5, [MAX_VOLUME_RATIO], subdivisions=2, on_step=lambda d, t: steps.append(t)
    )
    assert len(steps) == steps[-1] <= int(np.ceil(np.log(MAX_VOLUME_RATIO) / np.log(1.1)))
    assert point.converged
    theory = analytic_balloon_pressure(5.0, 0.01, 1e-4, 1e5)
    assert abs(point.pressure_pa / theory - 1) < 0.03


@pytest.mark.parametrize(
    ("command", "option", "value"),
    [
        ("indent", "--depth-mm", "nan"),
        ("indent", "--depth-mm", "inf"),
        ("indent", "--step-mm", "nan"),
        ("indent", "--speed-mm-s", "inf"),
        ("dome", "--depth-mm", "nan"),
        ("dome", "--volume-ratio", "inf"),
        ("indent", "--refine-radius-mm", "nan"),
        ("dome", "--refine-radius-mm", "inf"),
        ("dome", "--indenter-radius-mm", "nan"),
    ],
)
def test_fe_commands_refuse_non_finite_numbers(command: str, option: str, value: str) -> None:
    _usage_error(["fe", command, "--mesh-mm", "3", option, value], option)


@dataclass
class _Increment:
    depth: float
    force: np.ndarray
    converged: bool
    pressure: float = 4e3
    volume: float = 5e-6
    contact_area: float = 0.0
    newton_iterations: int = 3
    wall_s: float = 0.01


class _StallingModel:
    """Stands in for the inflated BioTac: its indentation stops at an increment that did not converge."""

    def indent(self, *args: object, **kwargs: object) -> list[_Increment]:
        return [_Increment(0.0, np.zeros(3), True), _Increment(1e-4, np.array([0.0, 0.0, 955.0]), False)]


@pytest.mark.parametrize("as_json", [False, True])
def test_indent_exits_1_after_a_failed_increment_with_or_without_json(
    monkeypatch: pytest.MonkeyPatch, as_json: bool
) -> None:
    from twin.cli import fe as cli_fe

    inflation = type("Inflation", (), {"volume_change": 0.0, "pressure": 0.0, "thickness": 0.0, "message": ""})
    model = _StallingModel()
    model.geometry = type("Geometry", (), {"skin": type("Skin", (), {"vertices": np.zeros((3, 3))})})
    monkeypatch.setattr(cli_fe, "_inflated_twin_model", lambda *_: (None, model, inflation))
    result = runner.invoke(app, ["fe", "indent", "--depth-mm", "0.1", *(["--json"] if as_json else [])])
    assert result.exit_code == 1, result.output
    assert "did not converge" in result.output
    if as_json:
        records = json.loads(result.stdout.strip().splitlines()[-1])
        assert [r["converged"] for r in records] == [True, False]


def test_learn_refuses_missing_empty_and_foreign_checkpoints(tmp_path: Path) -> None:
    _usage_error(["learn", "eval", str(tmp_path / "none.pt")], "no such checkpoint")
    empty = tmp_path / "empty.pt"
    empty.write_bytes(b"")
    _usage_error(["learn", "eval", str(empty)], "not a biotac-twin learn checkpoint")
    foreign = tmp_path / "foreign.pt"
    foreign.write_text("a text file")
    _usage_error(["learn", "eval", str(foreign)], "not a biotac-twin learn checkpoint")
    _usage_error(["learn", "predict", str(foreign), str(foreign)], "not a biotac-twin learn checkpoint")


def test_learn_train_reads_a_folder_of_campaign_files(tmp_path: Path) -> None:
    """A folder stands for its campaign files; a missing --data file or an empty folder is a usage error."""
    folder = tmp_path / "campaign"
    folder.mkdir()
    _usage_error(["learn", "train", str(folder), "--model", "mean"], "without campaign files")
    synth = runner.invoke(app, ["learn", "synth", str(folder / "biotac1.hdf5"), "--trajectories", "4"])
    assert synth.exit_code == 0, synth.output
    checkpoint = tmp_path / "mean.pt"
    args = ["learn", "train", str(folder), "--model", "mean", "--split", "none", "--out", str(checkpoint)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    from learn.checkpoint import Checkpoint

    assert [Path(p) for p in Checkpoint.load(checkpoint).training["files"]] == [folder / "biotac1.hdf5"]
    _usage_error(["learn", "eval", str(checkpoint), "--data", str(tmp_path / "gone.hdf5")], "no such file")


def _stop_before_fe(*args: object, **kwargs: object) -> None:
    raise ValueError("stopped before any FE work")


def test_nan_forces_are_counted_and_warned_never_dropped_in_silence(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two of the eight rows of a file get a NaN or infinite force: every reader says how many."""
    import h5py

    path = write_fake_campaign(tmp_path)
    checkpoint = tmp_path / "mean.pt"
    trained = runner.invoke(
        app, ["learn", "train", str(path), "--model", "mean", "--split", "none", "--out", str(checkpoint)]
    )
    assert trained.exit_code == 0, trained.output
    with h5py.File(path, "r+") as f:
        f["force/data"][1, 0] = np.nan
        f["force/data"][5, 2] = np.inf
    warning = "2 of 8 rows have NaN or infinite forces"
    scored = runner.invoke(app, ["learn", "eval", str(checkpoint), "--data", str(path), "--on", "all"])
    assert scored.exit_code == 0 and warning in scored.output, scored.output
    monkeypatch.setattr("twin.cli.common.model_or_nominal", _stop_before_fe)
    monkeypatch.setattr("twin.analysis.diagnose.diagnose", _stop_before_fe)
    readers = (["compare", str(path), "--out", str(tmp_path / "r")], ["validate", str(path)], ["diagnose", str(path)])
    for command in readers:
        result = runner.invoke(app, command)
        assert result.exit_code == 2 and "stopped before any FE work" in result.output, result.output
        assert warning in result.output.replace("\n", " "), result.output
