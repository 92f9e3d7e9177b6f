"""Same campaign, real protocols: a tiny campaign through HardwareBackend, over EGM/RWS/KMS40/BioTac SPI
on loopback against devices driven by the twin, writes the rows the SimBackend campaign of the same plan
writes, within sensor noise.

What may differ, and the tolerance for it (each a bound, or 5 sigmas of the noise the plant draws):
- joints: the simulation adds encoder noise (sigma 2e-5 rad); the simulated arms report exactly where
  EGM put them, which must be the planned joints. Tip and contact rows then differ by at most
  sum|dq| * 1 m (every lever from a YuMi joint axis to the tip is shorter than 1 m).
- electrodes and PDC: each run draws its own noise (electrode rows are tared, so a row carries the
  noise of two samples) and the twin's warm-up drift runs on wall time, not on the simulation's
  600 s trajectory slots; the drift each run saw is computed from the electrode model and removed.
- force rows: the noise of the row and of the tare sample, low-passed as the processing does, plus
  timing. The zero-phase 5 Hz filter leaks part of the *next* increment's step into each row; the
  simulation solves that step one tick after the row, the twin only after its solve (0.05-1 s), so
  the simulation's row leans further toward the next value, by at most `leak` of that step.
- time: the backend's clock (wall time on hardware); real time runs no faster than the commands.
The sensor rows are compared where the twin had settled: its solve for the row's pose had ended
SETTLE_S before the row (a solve takes 0.05-1 s, and seconds when the machine is busy; a row taken
sooner shows the previous state, a limit of the rehearsal, not of the hardware path). At least
MIN_SETTLED of the rows must qualify.
The skin is frictionless here so that the fe state at a row depends on the pose only: with friction
the skin remembers its path, and the fe solve at the loading/unloading reversal is sensitive enough
that it has converged in the simulated run and not in the twin's (whose joints differ by 1e-16 rad,
having been through EGM's degrees).
"""

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from multiprocessing import get_context
from pathlib import Path

import h5py
import numpy as np
import pytest

from fe.params import SkinParameters
from hardware.backend import HardwareBackend
from hardware.config import with_changes
from hardware.testbed import driven_testbed
from twin.backend import Backend, BackendError
from twin.campaign import QUICK_CONFIG, CampaignPlan, plan_campaign, run_campaign
from twin.campaign_hardware import HardwareCampaignResult, campaign_jobs, run_hardware_campaign
from twin.dataset import TRAJECTORY_FIELDS
from twin.loopback_rig import TWIN_WATCHDOG_S, TwinSources
from twin.plant import Plant, make_plant
from twin.processing import increment_ends, lowpass
from twin.protocol import QUICK_SETTINGS

SENSOR, INDENTER = 1, "sphere_medium"
SETTINGS = replace(QUICK_SETTINGS, normal_depth=0.4e-3, angled_depth=0.2e-3, standoff=0.5e-3, speed=2e-3, pause_s=1.2)
CONFIG = replace(QUICK_CONFIG, sensors=(SENSOR,), indenters=(INDENTER,), settings=SETTINGS)
K = 5.0  # noise sigmas
LEVER_M = 1.0  # bound on the distance (m) from any YuMi joint axis to the indenter tip
FE_FEATURES = {"fe_force", "fe_pressure", "fe_converged", "nodal_res", "mesh"}
SETTLE_S = 0.2  # s: over six time constants of the 5 Hz filter, and 20 BioTac frames
MIN_SETTLED = 0.75


def _plant() -> Plant:
    """Sensor 1 with a frictionless skin (see above) and no joint zero offsets: those put registration
    error at ~1 mm (the paper's band), more than these shallow paths go past the planned first contact."""
    return make_plant([SENSOR], CONFIG.seed, nominal=SkinParameters(friction=0.0), joint_offset_std=0.0)


@dataclass
class Runs:
    sim: h5py.File
    hw: h5py.File
    plan: CampaignPlan
    plant: Plant
    twin: TwinSources
    result: HardwareCampaignResult


def _run_hardware(plan: CampaignPlan, twin: TwinSources, out: Path) -> HardwareCampaignResult:
    with driven_testbed(twin, rws_port=0, kms40_port=0, egm_ports=(0, 0), biotac_port=0) as testbed:
        config = testbed.hardware_config(watchdog_s=TWIN_WATCHDOG_S)
        config = with_changes(config, egm={"startup_timeout_s": 5.0, "max_speed": 2.0})
        backend = HardwareBackend(config)
        try:
            return run_hardware_campaign(plan, out, backend)
        finally:
            backend.close()


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Runs]:
    out = tmp_path_factory.mktemp("hw_campaign")
    plant = _plant()
    # the simulated campaign runs in its own process meanwhile (it computes as fast as it can)
    sim = get_context("spawn").Process(target=run_campaign, args=(CONFIG, out / "sim", 1, plant))
    sim.start()
    try:
        plan = plan_campaign(CONFIG, plant)
        twin = TwinSources.for_campaign(CONFIG, SENSOR, INDENTER, plant)
        result = _run_hardware(plan, twin, out / "hw")
    except BaseException:
        sim.terminate()
        raise
    finally:
        sim.join(timeout=300)
    assert sim.exitcode == 0, "the simulated campaign failed"
    with h5py.File(out / "sim" / "biotac1.hdf5", "r") as f_sim, h5py.File(result.files[SENSOR], "r") as f_hw:
        yield Runs(f_sim, f_hw, plan, plant, twin, result)


def test_the_same_trajectories_and_row_layout(runs: Runs) -> None:
    sim, hw = runs.sim, runs.hw
    assert runs.result.ran == 2 and runs.result.incomplete == 0 and runs.result.stopped is None
    assert runs.twin.failures == []
    assert set(hw) == set(sim) - FE_FEATURES  # no fe model on a robot
    assert hw.attrs["indenter_names"] == sim.attrs["indenter_names"]
    for name in TRAJECTORY_FIELDS:  # ids, arm, geometry, registration, complete, first_row, n_rows
        np.testing.assert_array_equal(hw[f"trajectories/{name}"][:], sim[f"trajectories/{name}"][:], err_msg=name)
    assert hw["trajectories/complete"][:].all()
    for name in ("depth", "phase", "indenter_type", "trajectory_id"):
        np.testing.assert_array_equal(hw[f"{name}/data"][:], sim[f"{name}/data"][:], err_msg=name)
    for tid in sim["raw"]:  # the controller took as many ticks, with the same commands, on both
        for name in ("increment", "depth_command"):
            np.testing.assert_array_equal(hw[f"raw/{tid}/{name}"][:], sim[f"raw/{tid}/{name}"][:])


def test_the_file_keeps_the_estimated_registration_and_not_the_plants_error(runs: Runs) -> None:
    """The plan's registration error is the simulated plant's truth: a robot's file never holds it."""
    provenance = json.loads(runs.hw.attrs["provenance"])
    assert "registration_error_m" not in provenance
    for arm in ("left", "right"):
        np.testing.assert_array_equal(provenance["registration"][arm], runs.plan.registration[(SENSOR, arm)])


def test_joint_rows_are_the_plan_and_the_tip_follows(runs: Runs) -> None:
    sim, hw = runs.sim, runs.hw
    planned = {job.spec.trajectory_id: job.joint_path for job in runs.plan.planned}
    ids, depth_index = hw["trajectory_id/data"][:], _path_index(hw)
    expected = np.array([planned[t][k] for t, k in zip(ids, depth_index, strict=True)])
    q_hw, q_sim = hw["joint_angles/data"][:], sim["joint_angles/data"][:]
    np.testing.assert_allclose(q_hw, expected, rtol=0, atol=1e-9)  # EGM put the arm exactly there
    assert np.abs(q_sim - q_hw).max() < K * runs.plant.noise.encoder
    lever_bound = np.abs(q_sim - q_hw).sum(axis=1) * LEVER_M
    for name in ("tip_pos", "contact_loc"):
        error = np.linalg.norm(hw[f"{name}/data"][:] - sim[f"{name}/data"][:], axis=1)
        assert np.all(error <= lever_bound), name


def test_the_twin_settled_before_most_rows(runs: Runs) -> None:
    settled = _settled(runs.hw, runs.twin)
    lags = [round(solve.end - solve.start, 2) for solve in runs.twin.solves if solve.contact]
    assert settled.mean() >= MIN_SETTLED, f"settled rows {settled.astype(int)}; contact solves took {lags} s"


def test_electrode_and_pdc_rows_within_noise(runs: Runs) -> None:
    sim, hw = runs.sim, runs.hw
    ok = _settled(hw, runs.twin)
    model = runs.twin.backend.electrodes
    sigma = model.params.noise_std
    drift = {
        "sim": _drift_since_tare(sim, model.drift, 0.0),
        "hw": _drift_since_tare(hw, model.drift, runs.twin.clock_origin),
    }
    vals = {run: f["electrode_vals/data"][:] - drift[run][0] for run, f in (("sim", sim), ("hw", hw))}
    # rows are tared: noise of the row and of the tare sample in each run; +1 count of rounding
    tolerance = K * 2.0 * sigma + 1.0
    assert np.abs(vals["hw"] - vals["sim"])[ok].max() <= tolerance
    tare = {run: f["electrode_tare/data"][:] - drift[run][1] for run, f in (("sim", sim), ("hw", hw))}
    assert np.abs(tare["hw"] - tare["sim"]).max() <= K * np.sqrt(2.0) * sigma + 1.0
    assert np.abs(vals["sim"]).max() > 5 * tolerance, "the indentation must move the electrodes well beyond it"
    pdc_sigma = model.params.pdc_noise_std
    assert np.abs(hw["pdc/data"][:] - sim["pdc/data"][:])[ok].max() <= K * np.sqrt(2.0) * pdc_sigma + 1.0


def test_force_rows_within_noise_and_filter_timing(runs: Runs) -> None:
    sim, hw = runs.sim, runs.hw
    ok = _settled(hw, runs.twin)
    rate = SETTINGS.sample_rate_hz
    impulse = np.zeros(401)
    impulse[200] = 1.0
    gain2 = float(np.sum(lowpass(impulse, rate) ** 2))  # white-noise variance through the filter
    step = (np.arange(401) > 200).astype(float)
    leak = float(lowpass(step, rate)[200])  # a step one tick after a row, seen in that row
    # the row's filtered noise (the twin's readings may repeat: twice the variance) and the tare's
    sigma = runs.plant.noise.force * np.sqrt(gain2 + 1.0 + 2.0 * gain2 + 1.0)
    bound = K * sigma + leak * _next_row_step(sim)
    error = np.abs(hw["force/data"][:] - sim["force/data"][:])
    worst = np.unravel_index(np.where(ok[:, None], error / bound, 0.0).argmax(), error.shape)
    assert np.all(error[ok] <= bound[ok]), (
        f"force row {worst[0]} differs by {error[worst]:.3f} N > {bound[worst]:.3f} N"
    )
    assert np.abs(sim["force/data"][:]).max() > 3 * K * sigma, "the indentation must load the sensor beyond the noise"


def test_real_time_is_no_faster_than_the_commands(runs: Runs) -> None:
    sim, hw = runs.sim, runs.hw
    ids = sim["trajectory_id/data"][:]
    same = ids[1:] == ids[:-1]
    commanded = np.diff(sim["time/data"][:])[same]  # simulated seconds between rows
    waited = np.diff(hw["time/data"][:])[same]
    assert np.all(waited >= commanded - 1e-6)


def _path_index(f: h5py.File) -> np.ndarray:
    """Each row's index into its trajectory's joint path: the increment + 1 at the row sample."""
    index = []
    for tid, n in zip(f["trajectories/trajectory_id"][:], f["trajectories/n_rows"][:], strict=True):
        increment = f[f"raw/{tid}/increment"][:]
        rows = increment_ends(increment)
        assert len(rows) == n
        index.extend(increment[rows] + 1)
    return np.array(index)


def _drift_since_tare(
    f: h5py.File, drift: Callable[[float], np.ndarray], clock_origin: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per row, (drift at the row - drift at its trajectory's tare, drift at the tare) in counts.

    Times are the file's on the backend clock minus `clock_origin`: seconds since the electrode model's
    power-on (the simulation's clock is that already; the twin's started at `clock_origin`).
    """
    since, at_tare = [], []
    for tid, n in zip(f["trajectories/trajectory_id"][:], f["trajectories/n_rows"][:], strict=True):
        times = f[f"raw/{tid}/time"][:]
        rows = increment_ends(f[f"raw/{tid}/increment"][:])
        tare = drift(times[0] - clock_origin)
        for i in rows[:n]:
            since.append(drift(times[i] - clock_origin) - tare)
            at_tare.append(tare)
    return np.array(since), np.array(at_tare)


def _next_row_step(f: h5py.File) -> np.ndarray:
    """(R, 3) N: |unfiltered tared force at the next row - at this row| within a trajectory (0 at its end)."""
    steps = []
    sensor_in_biotac = f["trajectories/sensor_in_biotac"][:]
    for k, tid in enumerate(f["trajectories/trajectory_id"][:]):
        wrench = f[f"raw/{tid}/wrench"][:]
        force = (wrench[:, :3] - wrench[0, :3]) @ sensor_in_biotac[k][:3, :3].T
        at_rows = force[increment_ends(f[f"raw/{tid}/increment"][:])]
        steps.append(np.abs(np.diff(at_rows, axis=0, append=at_rows[-1:])))
    return np.concatenate(steps)


def _settled(f: h5py.File, twin: TwinSources) -> np.ndarray:
    """Per row: had the twin's last solve before the row started after the previous row (so: for this
    increment's pose) and ended SETTLE_S before the row? Times are `time.monotonic()` on both sides."""
    starts = np.array([solve.start for solve in twin.solves])
    ends = np.array([solve.end for solve in twin.solves])
    settled = []
    for tid in f["trajectories/trajectory_id"][:]:
        times = f[f"raw/{tid}/time"][:]
        rows = increment_ends(f[f"raw/{tid}/increment"][:])
        previous = times[np.concatenate([[0], rows[:-1]])]
        for before, at in zip(previous, times[rows], strict=True):
            last = np.searchsorted(starts, at) - 1
            settled.append(last >= 0 and starts[last] >= before and ends[last] <= at - SETTLE_S)
    return np.array(settled)


class _FaultAt:
    """A backend whose next advance raises BackendError once it is commanded to `joints` (a device that drops
    out just there), and every advance after that until `heal()`."""

    def __init__(self, backend: Backend, joints: np.ndarray) -> None:
        self.backend, self.joints, self.faulty = backend, joints, False
        self.attach_tool, self.read, self.close = backend.attach_tool, backend.read, backend.close

    def command_joints(self, arm: str, joints: np.ndarray) -> None:
        self.faulty |= np.array_equal(joints, self.joints)
        self.backend.command_joints(arm, joints)

    def advance(self, dt: float) -> None:
        if self.faulty:
            raise BackendError("F/T data is stale (0.5 s old); arms stopped; trajectory incomplete")
        self.backend.advance(dt)

    def heal(self) -> None:
        self.faulty = False


def test_a_fault_stops_the_campaign_keeps_the_cut_trajectory_and_a_rerun_resumes(tmp_path: Path) -> None:
    config = replace(CONFIG, mesh_max_edge=3e-3)
    plant = _plant()
    plan = plan_campaign(config, plant)
    first, second = campaign_jobs(plan)
    backend = _FaultAt(TwinSources.for_campaign(config, SENSOR, INDENTER, plant).backend, second.joint_path[3])
    mounts: list[tuple[str, str]] = []
    result = run_hardware_campaign(plan, tmp_path, backend, on_tool_change=lambda *mount: mounts.append(mount))
    assert mounts == [(first.arm, INDENTER)]  # one indenter, one arm: mounted once
    assert (result.ran, result.skipped, result.incomplete) == (2, 0, 1)
    assert result.stopped.startswith(f"trajectory {second.spec.trajectory_id} did not complete (backend fault: F/T")
    with h5py.File(result.files[SENSOR], "r") as f:
        assert f["trajectories/complete"][:].tolist() == [True, False]  # flushed and marked, not lost
        assert f["trajectories/n_rows"][1] == 2  # the increments before the fault
        assert "F/T data is stale" in f[f"raw/{second.spec.trajectory_id}"].attrs["message"]
    backend.heal()
    rerun = run_hardware_campaign(plan, tmp_path, backend)
    assert (rerun.ran, rerun.skipped, rerun.stopped) == (0, 2, None)  # both parts exist: a person decides
