"""Malformed campaign files (wrong shapes, missing groups, NaN, bad indices) fed to every command that reads
one: each ends with exit code 2 and a one-line error, no traceback, before any FE work."""

from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np
import pytest
from fake_campaign import write_fake_campaign
from typer.testing import CliRunner

from assets.indenters import INDENTERS
from twin.cli import app

runner = CliRunner()


@pytest.fixture(scope="module")
def valid_file(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tiny two-trajectory sensor file written by the campaign's own assembler."""
    return write_fake_campaign(tmp_path_factory.mktemp("fake"))


def _replace(key: str, value: Callable[[np.ndarray], np.ndarray]) -> Callable[[h5py.File], None]:
    def edit(f: h5py.File) -> None:
        data = value(f[key][()])
        del f[key]
        f[key] = data

    return edit


def _delete(key: str) -> Callable[[h5py.File], None]:
    def edit(f: h5py.File) -> None:
        del f[key]

    return edit


def _nan_at(index: tuple) -> Callable[[np.ndarray], np.ndarray]:
    def value(x: np.ndarray) -> np.ndarray:
        x = x.astype(float)
        x[index] = np.nan
        return x

    return value


READERS = ("dataset info", "compare", "validate", "diagnose", "calibrate", "view", "learn eval", "learn train")
REPLAY = ("compare", "validate", "diagnose", "calibrate")
"""The commands that replay trajectories: they need every group of docs/dataset.md, the others only some."""
MALFORMED: dict[str, tuple[Callable[[h5py.File], None], tuple[str, ...]]] = {
    "force with two columns": (_replace("force/data", lambda x: x[:, :2]), READERS),
    "fewer electrode rows than force rows": (_replace("electrode_vals/data", lambda x: x[:-1]), READERS),
    "n_rows beyond the data": (_replace("trajectories/n_rows", lambda x: x + 5), READERS),
    "negative first_row": (_replace("trajectories/first_row", lambda x: x - 1), READERS),
    "indenter index past the names": (_replace("trajectories/indenter_type", lambda x: x + len(INDENTERS)), READERS),
    "row indenter index past the names": (_replace("indenter_type/data", lambda x: x + len(INDENTERS)), READERS),
    "rows of another trajectory": (_replace("trajectory_id/data", lambda x: x[::-1].copy()), READERS),
    "missing trajectories group": (_delete("trajectories"), (*REPLAY, "view")),
    "missing raw recording": (_delete("raw/1"), READERS),
    "missing force feature": (_delete("force"), REPLAY),
    "missing electrode feature": (_delete("electrode_vals"), (*REPLAY, "learn eval", "learn train")),
    "short raw joints": (_replace("raw/0/joints", lambda x: x[:-1]), READERS),
    "NaN registration": (_replace("trajectories/registration", _nan_at((0, 0, 3))), READERS),
    "NaN raw time": (_replace("raw/1/time", _nan_at((2,))), READERS),
    "triangle index past the vertices": (_replace("mesh/triangles", lambda x: x + 100), READERS),
    "nodal field of another mesh": (_replace("nodal_res/data", lambda x: x[:, :5]), READERS),
    "indenter names missing": (lambda f: f.attrs.__delitem__("indenter_names"), REPLAY),
    "indenter names not JSON": (lambda f: f.attrs.__setitem__("indenter_names", "[sphere"), READERS),
    "sensor id not a number": (lambda f: f.attrs.__setitem__("sensor_id", "two"), READERS),
}
"""Each fault with the commands that must refuse it (those that read what it breaks)."""


@pytest.fixture(scope="module")
def checkpoint(valid_file: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A `mean` model trained on the valid file (for `twin learn eval --data BAD`)."""
    out = tmp_path_factory.mktemp("ckpt") / "mean.pt"
    result = runner.invoke(
        app,
        ["learn", "train", str(valid_file), "--model", "mean", "--split", "none"]
        + [
            "--out",
            str(out),
        ],
    )
    assert result.exit_code == 0, result.output
    return out


def _commands(path: Path, work: Path, checkpoint: Path) -> dict[str, list[str]]:
    return {
        "dataset info": ["dataset", "info", str(path)],
        "compare": ["compare", str(path), "--out", str(work / "report")],
        "validate": ["validate", str(path)],
        "diagnose": ["diagnose", str(path)],
        "calibrate": ["calibrate", str(path)],
        "view": ["view", str(path), "--save", str(work / "view.rrd")],
        "learn eval": ["learn", "eval", str(checkpoint), "--data", str(path)],
        "learn train": ["learn", "train", str(path), "--model", "mean", "--out", str(work / "m.pt")],
    }


def _assert_usage_error(args: list[str]) -> None:
    result = runner.invoke(app, args)
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2, (args, result.output, result.exception)
    assert isinstance(result.exception, SystemExit), (args, result.exception)
    assert "Traceback" not in result.output and len(errors) == 1, (args, result.output)


def test_the_fake_file_is_valid(valid_file: Path) -> None:
    result = runner.invoke(app, ["dataset", "info", str(valid_file), "--json"])
    assert result.exit_code == 0, result.output


@pytest.mark.parametrize("fault", list(MALFORMED))
def test_every_reader_refuses_a_malformed_file(fault: str, valid_file: Path, checkpoint: Path, tmp_path: Path) -> None:
    bad = tmp_path / "biotac2.hdf5"
    bad.write_bytes(valid_file.read_bytes())
    with h5py.File(bad, "r+") as f:
        edit, readers = MALFORMED[fault]
        edit(f)
    commands = _commands(bad, tmp_path, checkpoint)
    for name in readers:
        _assert_usage_error(commands[name])


@pytest.mark.parametrize("content", [None, b"", b"not hdf5 at all"])
def test_every_reader_refuses_a_missing_or_foreign_file(
    content: bytes | None, checkpoint: Path, tmp_path: Path
) -> None:
    path = tmp_path / "biotac2.hdf5"
    if content is not None:
        path.write_bytes(content)
    for name, args in _commands(path, tmp_path, checkpoint).items():
        if name == "view" and content is None:
            continue  # typer itself refuses a missing view path (exit 2, its own message box)
        _assert_usage_error(args)
