"""Replays of many trajectories of one model as one batched run (`Predictor.prefetch`) equal the
one-at-a-time replays, failures included; those of many models as one run (`Predictor.prefetch_many`)
equal the one-model runs; `--device` of the analysis commands (issue 18)."""

import json
import multiprocessing
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import warp as wp
from typer.testing import CliRunner

from fe.batched_runner import run_trajectories
from fe.params import NewtonSettings, SkinParameters
from fe.sensor import BioTacModel
from twin.analysis import predict
from twin.analysis.data import CampaignData, load_campaign
from twin.analysis.predict import Prediction, Predictor, TwinModel, fill_holds, held_solves, replay_workers
from twin.cli import app

FRICTIONLESS_TOLERANCE = 1e-6
"""Largest force difference, as a fraction of the trajectory's largest force, without friction."""
FRICTION_LAG_TOLERANCE = 1e-3
"""The same with friction (the lagged friction is converged only to this)."""
HOLD_FILL_TOLERANCE_N, HOLD_FILL_TOLERANCE_COUNTS = 0.5e-3, 0.05
"""Largest force (N) and PDC (counts) difference between a relaxing replay whose holds are solved at their first
and last events and filled with the relaxation's exponential and one solved at every event: 5 % of the F/T noise
(10 mN) and of the PDC's (1 count). Measured on this campaign: 0.29 mN at a relaxing fraction of 0.4 and 0.5 s,
0.09 mN at 0.15 / 1 s, 0.17 mN at 0.6 / 3 s; 0.023 counts (the skin's response is not exactly one exponential:
friction and the fluid)."""
MANY_MODELS_TOLERANCE = 1e-9
"""Largest force difference, as a fraction of the trajectory's largest force, between a replay solved in a
batch of many models and in a batch of its own model: each system iterates on its own, so only the order
of floating-point sums may differ."""


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory, make_tiny_campaign) -> Path:
    return make_tiny_campaign(tmp_path_factory.mktemp("batched_replay"))


@pytest.fixture(scope="module")
def data(tiny: Path) -> CampaignData:
    return load_campaign(tiny)


def _both_ways(
    model: TwinModel, data: CampaignData, workers: int | None = None
) -> tuple[list[Prediction], list[Prediction]]:
    """Predictions of every trajectory replayed one at a time, and after one batched prefetch (on `workers`
    processes; default one per usable CPU)."""
    single = [Predictor("cpu").predict(model, t) for t in data.trajectories]
    batched = Predictor("cpu", workers=workers)
    assert batched.prefetch(model, data.trajectories) == len(data.trajectories)
    assert batched.prefetch(model, data.trajectories) == 0  # all cached: nothing left to solve
    return single, [batched.predict(model, t) for t in data.trajectories]


def _assert_same(single: list[Prediction], batched: list[Prediction], tolerance: float) -> None:
    for one, many in zip(single, batched, strict=True):
        np.testing.assert_array_equal(one.converged, many.converged)
        scale = np.nanmax(np.linalg.norm(one.increment_force, axis=1))
        assert scale > 0.05  # the path presses the skin
        reached = one.converged
        np.testing.assert_allclose(many.increment_force[reached], one.increment_force[reached], atol=tolerance * scale)
        assert np.isnan(many.increment_force[~reached]).all() and np.isnan(many.increment_pressure[~reached]).all()
        np.testing.assert_allclose(many.force_fullrate, one.force_fullrate, atol=tolerance * scale)


@pytest.fixture(scope="module")
def nominal(data: CampaignData) -> tuple[list[Prediction], list[Prediction]]:
    """The nominal model (friction 0.186) both ways."""
    return _both_ways(TwinModel(mesh_max_edge=data.mesh_max_edge), data)


def test_a_batched_prefetch_replays_like_one_trajectory_at_a_time(
    data: CampaignData, nominal: tuple[list[Prediction], list[Prediction]]
) -> None:
    frictionless = TwinModel(skin=replace(SkinParameters(), friction=0.0), mesh_max_edge=data.mesh_max_edge)
    for (single, batched), tolerance in (
        (_both_ways(frictionless, data), FRICTIONLESS_TOLERANCE),
        (nominal, FRICTION_LAG_TOLERANCE),
    ):
        assert all(p.converged.all() for p in single)
        _assert_same(single, batched, tolerance)


def test_a_relaxing_skin_is_replayed_in_batch_at_the_recorded_times(
    data: CampaignData, nominal: tuple[list[Prediction], list[Prediction]]
) -> None:
    model = TwinModel(effects={"skin_relaxation": {"fraction": 0.4, "time_s": 0.5}}, mesh_max_edge=data.mesh_max_edge)
    single, batched = _both_ways(model, data)
    _assert_same(single, batched, FRICTION_LAG_TOLERANCE)
    elastic = nominal[0][0].increment_force
    deepest = np.nanargmax(np.linalg.norm(elastic, axis=1))
    relaxed = np.linalg.norm(batched[0].increment_force[deepest])
    assert relaxed < np.linalg.norm(elastic[deepest])  # the relaxed skin pushes back less


def test_a_batched_replay_stops_at_the_first_failure_like_the_single_one(
    data: CampaignData, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With Newton allowed only a few iterations the skin fails where the indenter first presses: both ways
    keep the increments before it and nothing after (solved in this process: the patch does not reach worker
    processes)."""
    inflated_skin = BioTacModel.inflated_skin
    impatient = NewtonSettings(max_iterations=4)
    monkeypatch.setattr(BioTacModel, "inflated_skin", lambda self: replace(inflated_skin(self), newton=impatient))
    single, batched = _both_ways(TwinModel(mesh_max_edge=data.mesh_max_edge), data, workers=1)  # patched here
    for one in single:
        failed = np.flatnonzero(~one.converged)
        assert failed.size and failed[0] > 0 and (failed == np.arange(failed[0], len(one.converged))).all()
    for one, many in zip(single, batched, strict=True):
        np.testing.assert_array_equal(one.converged, many.converged)
        np.testing.assert_allclose(many.increment_force[one.converged], one.increment_force[one.converged], atol=1e-9)


@pytest.mark.parametrize("command", ["compare", "validate", "calibrate", "diagnose", "improve"])
def test_an_unknown_device_is_one_line_and_exit_code_2(tiny: Path, tmp_path: Path, command: str) -> None:
    extra = {"compare": ["--out", str(tmp_path / "r")], "improve": ["--add", "ft_gain"]}.get(command, [])
    result = CliRunner().invoke(app, [command, str(tiny), *extra, "--device", "nodevice"])
    assert result.exit_code == 2, result.output
    assert "nodevice" in result.output and "Traceback" not in result.output


def test_cuda_where_there_is_none_is_one_line_on_stderr(tiny: Path, tmp_path: Path) -> None:
    """Warp's native library prints its CUDA errors past Python's stderr: the command's refusal is still one
    line (a subprocess sees file descriptor 2)."""
    device = "cuda" if not wp.is_cuda_available() else f"cuda:{wp.get_cuda_device_count()}"
    command = [sys.executable, "-c", "from twin.cli import app; app()", "compare", str(tiny), "--out", str(tmp_path)]
    result = subprocess.run([*command, "--device", device], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip().splitlines() == [result.stderr.strip()] and device in result.stderr


def test_validate_on_the_cpu_device_gives_its_table(tiny: Path) -> None:
    result = CliRunner().invoke(app, ["validate", str(tiny), "--device", "cpu", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.output.strip().splitlines()[-1])
    rows = [(t["rows_reached"], t["rows_total"]) for t in summary["trajectories"]]
    assert len(rows) == 2 and all(reached == total > 0 for reached, total in rows)  # predicted to the end


def test_a_prefetch_of_many_models_replays_like_one_model_at_a_time(
    data: CampaignData, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Elastic and relaxing skins in one batched run (one thread: the elastic replays given their events'
    times) replay like each model alone, the elastic ones in untimed runs of their own."""
    nominal = TwinModel(mesh_max_edge=data.mesh_max_edge)
    models = [
        nominal,
        nominal.with_effects({"skin_modulus": {"scale": 1.2}}),
        nominal.with_effects({"skin_thickness": {"scale": 0.9}}),
        nominal.with_effects({"ft_gain": {"scale": 1.05}}),  # a measurement effect: the nominal replays
        nominal.with_effects({"skin_relaxation": {"fraction": 0.4, "time_s": 0.5}}),  # timed, in the same run
    ]
    one_model = Predictor("cpu")
    solved = [one_model.prefetch(m, data.trajectories) for m in models]
    assert solved == [len(data.trajectories)] * 3 + [0, len(data.trajectories)]
    many_models = Predictor("cpu", workers=1)
    runs = []
    monkeypatch.setattr(predict, "run_trajectories", lambda *a, **k: runs.append(a[1]) or run_trajectories(*a, **k))
    assert many_models.prefetch_many([(m, data.trajectories) for m in models]) == sum(solved)
    assert len(runs) == 1 and all(t.times is not None for t in runs[0])  # one timed run for every skin
    assert many_models.prefetch_many([(m, data.trajectories) for m in models]) == 0  # all cached
    forces = []
    for model in models:
        single = [one_model.predict(model, t) for t in data.trajectories]
        batched = [many_models.predict(model, t) for t in data.trajectories]
        _assert_same(single, batched, MANY_MODELS_TOLERANCE)
        forces.append(np.concatenate([p.increment_force for p in single]))
    # the models' replays differ: each system solved its own skin, not its neighbour's
    assert np.nanmax(np.abs(forces[1] - forces[0])) > 1e-3 and np.nanmax(np.abs(forces[2] - forces[0])) > 1e-3


def test_a_prefetch_split_over_worker_processes_replays_bit_for_bit_like_one_run(data: CampaignData) -> None:
    nominal = TwinModel(mesh_max_edge=data.mesh_max_edge)
    models = [
        nominal,
        nominal.with_effects({"skin_modulus": {"scale": 1.2}}),
        nominal.with_effects({"skin_relaxation": {"fraction": 0.4, "time_s": 0.5}}),  # timed: a run of its own
    ]
    requests = [(m, data.trajectories) for m in models]
    one_run, threaded = Predictor("cpu", workers=1), Predictor("cpu", workers=3)
    assert one_run.workers == 1 and threaded.workers == 3
    assert Predictor("cuda").workers == predict.GPU_WORKERS and Predictor("cuda", workers=1).workers == 1
    done: list[tuple[int, int]] = []
    n = len(models) * len(data.trajectories)
    assert one_run.prefetch_many(requests) == threaded.prefetch_many(requests, lambda *d: done.append(d)) == n
    assert sorted(done) == [(k, n) for k in range(1, n + 1)]  # each replay told once, from whichever worker
    for model in models:
        for t in data.trajectories:
            one, split = one_run.predict(model, t), threaded.predict(model, t)
            np.testing.assert_array_equal(split.increment_force, one.increment_force)
            np.testing.assert_array_equal(split.pdc_fullrate, one.pdc_fullrate)


def test_a_replay_worker_that_dies_is_one_clear_error_and_the_next_batch_starts_new_workers(
    data: CampaignData,
) -> None:
    nominal = TwinModel(mesh_max_edge=data.mesh_max_edge)
    predictor = Predictor("cpu", workers=2)
    replay_workers(2)  # started (or already running in this process)
    workers = [child for child in multiprocessing.active_children() if child.name.startswith("SpawnProcess")]
    assert workers
    for worker in workers:
        worker.kill()
        worker.join()
    with pytest.raises(RuntimeError, match="replay worker process died"):
        predictor.prefetch(nominal, data.trajectories)
    assert predictor.prefetch(nominal, data.trajectories) == len(data.trajectories)  # new workers
    assert np.isfinite(predictor.predict(nominal, data.trajectories[0]).increment_force).all()


def _job(skin: int, events: int, mesh: float = 2e-3) -> predict._ReplayJob:
    """A replay job of skin number `skin` with `events` solves on fe mesh `mesh` (m) (only what `_shares` and
    `_device_shares` read is real)."""
    times = (np.zeros(events), np.zeros(events))
    key = ((skin,), mesh, "thickness")
    plan = predict._ReplayPlan(key, np.zeros((events, 3)), np.eye(3), times, False, np.ones(events, bool), 1.0)
    return predict._ReplayJob(SkinParameters(), mesh, "thickness", "sphere_small", np.eye(3), plan)


def _each_once(shares: list[list[predict._ReplayJob]], jobs: list[predict._ReplayJob]) -> bool:
    return sorted(id(job) for share in shares for job in share) == sorted(map(id, jobs))


def test_a_batch_is_shared_out_by_whole_skins_when_there_are_enough_else_by_replay() -> None:
    many = [_job(skin, events) for skin in range(6) for events in (10 + skin, 20)]  # 6 skins, 2 workers: by skin
    shares = predict._shares(many, 2)
    assert len(shares) == 2 and _each_once(shares, many)
    skins = [{job.model_key for job in share} for share in shares]
    assert not skins[0] & skins[1]  # no skin inflated by both workers
    loads = [sum(job.events for job in share) for share in shares]
    assert abs(loads[0] - loads[1]) <= 36  # within the largest skin's solves
    few = [_job(skin, events) for skin in range(3) for events in (5, 30, 12, 40)]  # 3 skins, 2 workers: by replay
    shares = predict._shares(few, 2)
    assert len(shares) == 2 and _each_once(shares, few)
    loads = [sum(job.events for job in share) for share in shares]
    assert abs(loads[0] - loads[1]) <= 5  # 261 solves: 132 and 129 (the longest first, each to the lighter share)
    assert [len(share) for share in predict._shares(few[:1], 4)] == [1]  # never an empty share


def test_a_gpu_batch_is_shared_out_by_mesh_first_then_halved() -> None:
    fine = [_job(skin, 40, 0.5e-3) for skin in range(3)]  # a mixed wave: the model mesh's replays and
    coarse = [_job(skin, 30 + skin, 1e-3) for skin in range(3, 23)]  # the ranking mesh's columns
    two = predict._device_shares(fine + coarse, 2)
    assert _each_once(two, fine + coarse)
    assert sorted(len(share) for share in two) == [3, 20]  # each mesh apart, side by side
    assert all(len({job.mesh_max_edge for job in share}) == 1 for share in two)
    three = predict._device_shares(fine + coarse, 3)  # the spare worker halves the larger mesh's share
    assert _each_once(three, fine + coarse) and sorted(len(share) for share in three) == [3, 10, 10]
    assert all(len({job.mesh_max_edge for job in share}) == 1 for share in three)
    one = predict._device_shares(fine + coarse, 1)  # more meshes than workers: one share of every job
    assert len(one) == 1 and _each_once(one, fine + coarse)
    assert [len(share) for share in predict._device_shares(fine[:1], 4)] == [1]  # never an empty share


def test_held_poses_are_solved_at_their_first_events_and_their_last() -> None:
    indices = np.r_[np.full(50, 3), 4, np.full(3, 5)]  # a 5 s pause's 50 events, a move, a short pause
    assert np.flatnonzero(held_solves(indices)).tolist() == [0, 49, 50, 51, 53]
    assert np.flatnonzero(held_solves(indices, 3)).tolist() == [0, 1, 2, 49, 50, 51, 52, 53]
    assert held_solves(indices, 10**9).all()


def test_filled_holds_follow_one_exponential_exactly() -> None:
    tau, times = 0.7, np.arange(20) * 0.1
    indices = np.zeros(20, dtype=int)
    decay = 2.0 + 3.0 * np.exp(-times / tau)  # one Prony branch's decay at a held pose
    values = np.column_stack([decay, -decay])
    for first in (1, 5):
        solved = held_solves(indices, first)
        blank = np.where(solved[:, None], values, np.nan)
        np.testing.assert_allclose(fill_holds(times, solved, blank, tau), values, rtol=1e-12)
    blank[19] = np.nan  # a failed solve (the last): what is filled from it is NaN, the rest is kept
    filled = fill_holds(times, solved, blank, tau)
    assert np.isnan(filled[5:]).all() and np.isfinite(filled[:5]).all()


def test_a_relaxing_replay_solving_its_holds_sparsely_matches_solving_every_event(
    tmp_path_factory: pytest.TempPathFactory, make_tiny_campaign
) -> None:
    """1.6 s pauses: the replay solves 2 of each pause's 16 events; the plant's schedule, every 0.1 s, is the
    reference. Held poses depend on time alone (the friction's stick anchors), so both agree to the exponential
    fill's tolerance, far below the F/T noise."""
    data = load_campaign(make_tiny_campaign(tmp_path_factory.mktemp("long_pauses"), pause_s=1.6))
    model = TwinModel(effects={"skin_relaxation": {"fraction": 0.4, "time_s": 0.5}}, mesh_max_edge=data.mesh_max_edge)
    sparse = [Predictor("cpu").predict(model, t) for t in data.trajectories]
    dense = [Predictor("cpu", held_first=10**9).predict(model, t) for t in data.trajectories]
    for few, every in zip(sparse, dense, strict=True):
        assert every.converged.all() and few.converged.all()
        assert np.abs(every.force_fullrate - every.force_fullrate[0]).max() > 0.05  # it presses
        np.testing.assert_allclose(few.force_fullrate, every.force_fullrate, atol=HOLD_FILL_TOLERANCE_N)
        np.testing.assert_allclose(few.pdc_fullrate, every.pdc_fullrate, atol=HOLD_FILL_TOLERANCE_COUNTS)


def test_a_predictor_without_electrodes_predicts_force_and_pdc_alike_and_gives_no_rows(data: CampaignData) -> None:
    """`Predictor(electrodes=False)` (the residual's analyses): the same replays, force and PDC bit for bit, in one
    batch (on worker processes: the flag travels with each job) and one at a time, but no electrode counts, and
    asking it for rows is a one-line error rather than NaN electrodes."""
    model = TwinModel(mesh_max_edge=data.mesh_max_edge)
    reading, blind = Predictor("cpu", workers=1), Predictor("cpu", workers=2, electrodes=False)
    assert blind.prefetch(model, data.trajectories) == len(data.trajectories)
    alone = Predictor("cpu", workers=1, electrodes=False)
    for t in data.trajectories:
        full = reading.predict(model, t)
        for other in (blind.predict(model, t, rows=False), alone.predict(model, t, rows=False)):
            np.testing.assert_array_equal(other.force_fullrate, full.force_fullrate)
            np.testing.assert_array_equal(other.pdc_fullrate, full.pdc_fullrate)
        assert np.isfinite(full.rows.electrode_vals).all()
        key = blind._plan(model, t).key
        assert np.isnan(blind._replays[key].electrodes).all() and np.isfinite(reading._replays[key].electrodes).all()
        with pytest.raises(ValueError, match="reads no electrodes"):
            blind.predict(model, t)
