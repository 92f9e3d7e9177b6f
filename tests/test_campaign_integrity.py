"""Campaign data integrity without FE: a resume never mixes campaigns, workers die with their parent, a
terminated run cleans up and says it can resume, writers never share a temporary file, a short disk is
reported before any HDF5 is written, and a bad --out is a one-line usage error."""

import errno
import os
import signal
import subprocess
import sys
import textwrap
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from fake_campaign import SKIN, VERTICES, write_fake_parts
from typer.testing import CliRunner

from twin.campaign import QUICK_CONFIG, campaign_options, claim_parts, run_campaign
from twin.cli import app
from twin.dataset import assemble_sensor_file, read_part, write_part
from twin.plant import make_plant

runner = CliRunner()
CONFIG = replace(QUICK_CONFIG, sensors=(2,), indenters=("sphere_medium",))
QUICK_ARGS = ["campaign", "run", "--quick", "--sensors", "2", "--indenters", "sphere_medium", "--workers", "1"]
"""The CLI spelling of CONFIG (seed 0, 2 mm mesh)."""


def _usage_error(args: list[str], *needles: str) -> str:
    result = runner.invoke(app, args)
    errors = [line for line in result.output.splitlines() if line.startswith("error:")]
    assert result.exit_code == 2 and isinstance(result.exception, SystemExit), (result.output, result.exception)
    assert len(errors) == 1 and all(n in result.output.replace("\n", " ") for n in needles), result.output
    return result.output


def _seed0_folder(tmp_path: Path) -> Path:
    """An --out folder holding a fake part of the seed-0 quick campaign CONFIG, as a killed run leaves it."""
    out = tmp_path / "seed0"
    claim_parts(out / "parts", campaign_options(CONFIG, make_plant([2], 0)))
    write_fake_parts(out / "parts", trajectories=1)
    return out


@pytest.mark.parametrize(
    ("options", "named"),
    [
        (["--seed", "1"], "--seed: 0 there, 1 here"),
        (["--mesh-mm", "3"], "--mesh-mm: 2 there, 3 here"),
        (["--indenters", "sphere_large"], "--indenters: sphere_medium there, sphere_large here"),
    ],
)
def test_resume_with_other_options_names_the_difference(tmp_path: Path, options: list[str], named: str) -> None:
    """The issue's reproductions (another seed, another mesh) refuse before running anything."""
    out = _seed0_folder(tmp_path)
    _usage_error([*QUICK_ARGS, "--out", str(out), *options], named, "--restart")
    assert not list(out.glob("*.hdf5")) and len(list((out / "parts").rglob("*.npz"))) == 1


def test_parts_without_their_options_are_refused(tmp_path: Path) -> None:
    out = tmp_path / "old"
    write_fake_parts(out / "parts", trajectories=1)
    _usage_error([*QUICK_ARGS, "--out", str(out)], "without a record of their options", "--restart")


def test_a_part_made_by_another_campaign_is_refused(tmp_path: Path) -> None:
    """Each part carries the digest of its options; a stray one in a matching folder is caught."""
    out = _seed0_folder(tmp_path)
    with pytest.raises(ValueError, match="made with other campaign options"):
        run_campaign(CONFIG, out, plant=make_plant([2], 0))


def test_restart_discards_the_old_parts(tmp_path: Path) -> None:
    out = _seed0_folder(tmp_path)
    seed1 = campaign_options(replace(CONFIG, seed=1), make_plant([2], 1))
    claim_parts(out / "parts", seed1, restart=True)
    assert not list((out / "parts").rglob("*.npz"))
    claim_parts(out / "parts", seed1)  # now the folder is seed 1's


def test_bad_out_is_a_usage_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    a_file = tmp_path / "file"
    a_file.write_text("x")
    _usage_error([*QUICK_ARGS, "--out", str(a_file)], "is a file")
    _usage_error([*QUICK_ARGS, "--out", str(a_file / "sub")], "not a writable folder")

    def read_only(*args: object, **kwargs: object) -> None:
        raise OSError(errno.EROFS, "Read-only file system")

    monkeypatch.setattr("tempfile.TemporaryFile", read_only)
    _usage_error([*QUICK_ARGS, "--out", str(tmp_path / "ro")], "Read-only file system")


def test_a_device_warp_cannot_use_is_a_usage_error(tmp_path: Path) -> None:
    """`--device` (the batched campaign) is checked before anything is planned or written."""
    _usage_error([*QUICK_ARGS, "--out", str(tmp_path / "out"), "--device", "abacus"], "warp device 'abacus'")
    assert not (tmp_path / "out").exists()


def test_interrupted_run_says_it_can_resume(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def interrupted(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr("twin.campaign.run_campaign", interrupted)
    result = runner.invoke(app, [*QUICK_ARGS, "--out", str(tmp_path / "run")])
    assert result.exit_code == 130, result.output
    assert "interrupted" in result.output and "resume" in result.output


def test_a_writer_never_touches_another_writers_temporary_file(tmp_path: Path) -> None:
    """A temporary file at the part's name + .tmp (another writer's, mid-write) survives a write_part."""
    part = tmp_path / "trajectory_000000.npz"
    other = part.with_name(part.name + ".tmp")
    other.write_bytes(b"another writer's half-written part")
    write_part(part, {"x": np.arange(3)})
    assert other.read_bytes() == b"another writer's half-written part"
    np.testing.assert_array_equal(read_part(part)["x"], np.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == [part.name, other.name]


def test_a_killed_writers_temporary_files_are_removed_by_the_next_run(tmp_path: Path) -> None:
    """A process killed mid-write (a sensor file on the campaign's file thread, a part on a worker) leaves its
    temporary file; the next run removes it, and leaves a running writer's and any other file alone."""
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)  # exited: no process has this id now (ids are not reused this soon)
    out = tmp_path / "run"
    (out / "parts" / "biotac2").mkdir(parents=True)
    stale = [
        out / f"biotac2.hdf5.{dead_pid}-0123abcd.tmp",
        out / "parts" / "biotac2" / f"trajectory_000001.npz.{dead_pid}-89abcdef.tmp",
    ]
    alive = out / f"biotac3.hdf5.{os.getpid()}-fedcba98.tmp"
    other = out / "notes.tmp"
    for path in [*stale, alive, other]:
        path.write_bytes(b"half-written")

    def stop(*_: object) -> None:  # stopped at planning, right after the start-up checks
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_campaign(CONFIG, out, workers=1, on_plan=stop)
    assert not any(path.exists() for path in stale)
    assert alive.exists() and other.exists()


def test_a_short_disk_is_reported_before_writing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    parts = write_fake_parts(tmp_path / "parts")
    size = sum(p.stat().st_size for p in parts)
    usage = type("Usage", (), {"total": 10 * size, "used": 10 * size - size // 2, "free": size // 2})
    monkeypatch.setattr("shutil.disk_usage", lambda _: usage)
    out = tmp_path / "biotac2.hdf5"
    with pytest.raises(ValueError, match="not enough free disk space"):
        assemble_sensor_file(parts, out, 2, ["sphere_medium"], {}, SKIN.faces, VERTICES[:, 2] < 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["parts"]


def test_a_failed_write_leaves_no_temporary_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A disk that fills mid-write: one clear ValueError, no .tmp and no sensor file left."""
    import h5py

    parts = write_fake_parts(tmp_path / "parts")
    create = h5py.Group.create_dataset

    def fill_up(self: h5py.Group, name: str, *args: object, **kwargs: object) -> h5py.Dataset:
        if name.startswith("force"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return create(self, name, *args, **kwargs)

    monkeypatch.setattr(h5py.Group, "create_dataset", fill_up)
    with pytest.raises(ValueError, match="No space left on device.*parts are kept"):
        assemble_sensor_file(parts, tmp_path / "biotac2.hdf5", 2, ["sphere_medium"], {}, SKIN.faces)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["parts"]


WORKER_MODULE = """
import os
import time


def setup():
    pass


def task(path):
    with open(path, "w") as handle:
        handle.write(str(os.getpid()))
    time.sleep(600)
"""
PARENT_SCRIPT = """
import sys

import sleepy
from twin.cli.common import sigterm_as_interrupt
from twin.executors import LocalExecutor

try:
    with sigterm_as_interrupt():
        list(LocalExecutor(1).map_unordered(sleepy.task, [(sys.argv[1],)], sleepy.setup, ()))
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(130)
"""


def _alive(pid: int) -> bool:
    """Whether process `pid` runs (a zombie waiting for its reaper counts as dead)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    return not stat.exists() or stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"


def _wait_for(condition, timeout: float) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.1)
    return False


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_workers_die_with_their_parent(tmp_path: Path, sig: signal.Signals) -> None:
    """A local executor's worker, busy for 10 minutes, ends within seconds of its parent being killed
    (SIGKILL: no clean-up can run) or terminated (SIGTERM: the parent ends its workers and says so)."""
    (tmp_path / "sleepy.py").write_text(textwrap.dedent(WORKER_MODULE))
    pid_file = tmp_path / "worker.pid"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.getcwd()])}
    parent = subprocess.Popen(
        [sys.executable, "-c", PARENT_SCRIPT, str(pid_file)], env=env, stdout=subprocess.PIPE, text=True
    )
    worker = None
    try:
        assert _wait_for(lambda: pid_file.exists() and pid_file.read_text(), 60), "the worker never started"
        worker = int(pid_file.read_text())
        parent.send_signal(sig)
        out, _ = parent.communicate(timeout=30)
        assert _wait_for(lambda: not _alive(worker), 10), "the worker outlived its parent"
        if sig == signal.SIGTERM:
            assert parent.returncode == 130 and "interrupted" in out
    finally:
        parent.kill()
        if worker is not None and _alive(worker):
            os.kill(worker, signal.SIGKILL)
