"""The loopback rig: the twin drives simulated devices; the F/T sensor and the BioTac stream what it computes.

`TwinSources` owns a `twin.sim_backend.SimBackend` of one plant sensor (the same plant, skin model,
electrode model and noise a simulated campaign uses) and keeps it in step with simulated arms (the
EGM arms of `hardware.testbed.SimulatedTestbed`, which `hardware.testbed.driven_testbed` hands it;
this module imports nothing of `hardware`). A thread, every `poll_s`:

- reads both arms' joints (rad, chain order: what the encoders read; the plant's joint zero offsets
  put the true arm elsewhere, as in a simulated campaign) and makes them the SimBackend's targets,
  then advances it by the wall time since the last poll (so electrode drift runs in real time). The SimBackend
  solves the skin whenever the indenter stands at a new pose: out of contact that costs nothing, and
  in contact the protocol's 0.1 mm increments take one EGM cycle, so each increment is one solve at
  the pose `SimBackend` solves in a simulated campaign;
- takes the arm whose indenter tip is nearest the BioTac, once within `ENGAGE_M`, as the
  indenting one (the indenter is mounted on both flanges; when that arm changes the skin starts
  from rest, as after a tool change);
- publishes one noisy reading (`SimBackend.read`). The sensors' sources return the latest one:
  `wrench()` (6,) N, N·m, F/T sensor frame, untared; `electrodes()` ((19,) counts, PDC counts). They
  never wait for a solve, so a slow solve delays the new load, never the streams.

A contact solve takes 0.05-1 s on a busy desktop core (2 mm mesh; the first touch of a path is the
slowest, and its Newton iterations, 2 to 12, change with 1e-16 rad differences in the joints), so the
twin's load lags the arm by that much: protocol pauses must be longer for the recorded rows to see
the settled state; `solves` says when each solve ran. A solve
that fails (no convergence) is recorded in `failures`; the readings hold until the indenting arm
moves on, and the skin restarts from rest there.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Mapping
from typing import NamedTuple, Protocol

import numpy as np

from assets.biotac import make_biotac
from twin.backend import ARMS, BackendError
from twin.campaign import CampaignConfig, plant_sensor_models, true_biotac_pose
from twin.kinematics import forward
from twin.planning import scene_tool_tip
from twin.plant import Plant, make_plant
from twin.scene import TestbedScene
from twin.sim_backend import SimBackend

TWIN_STREAM = 0x7717
"""Salt of the twin's noise stream: SeedSequence([seed, sensor_id, TWIN_STREAM])."""
POLL_S = 0.01
"""Default period (s) of following the arms and publishing a reading: the BioTac's 100 Hz frame rate."""
ENGAGE_M = 0.1
"""An arm's indenter tip this close (m) to the BioTac frame's origin, and nearer than the other's, indents."""
SOLVE_LOG = 100_000
"""How many of the latest solves `TwinSources.solves` keeps."""
TWIN_WATCHDOG_S = 0.5
"""Stale-data limit (s) for rehearsing against twin-driven devices: the twin solves in the devices'
process, whose streams then wait on Python's GIL now and then (273 ms seen on a busy 2-core machine,
where the bench's 0.1 s stops the arms)."""


class Arm(Protocol):
    """A simulated arm the twin follows: its joints (7,) rad, chain order, as its encoders read them."""

    @property
    def joints(self) -> np.ndarray: ...


class Solve(NamedTuple):
    """One skin solve of the twin: `time.monotonic()` (s) at its start and end; False when out of contact."""

    start: float
    end: float
    contact: bool


class TwinSources:
    """Wrench and electrode sources computed by `backend`, which follows the arms given to `follow`.

    `indenter` is mounted on both arms of `backend`'s scene. Until `follow` starts, the sources return
    the rest reading.
    """

    def __init__(self, backend: SimBackend, indenter: str, poll_s: float = POLL_S) -> None:
        if not poll_s > 0:
            raise ValueError(f"poll_s must be > 0, got {poll_s!r}")
        self.backend = backend
        self.indenter = indenter
        self.poll_s = poll_s
        for arm in ARMS:  # the last one attached indents first
            backend.attach_tool(arm, indenter)
        self._active = ARMS[-1]
        self._tool_tip = scene_tool_tip(backend.scene, indenter)
        self._latest = backend.read()
        self.stats: Counter[str] = Counter()
        """polls, arm_switches."""
        self.solves: deque[Solve] = deque(maxlen=SOLVE_LOG)
        """The latest skin solves, in order: when each ran and whether the skin was in contact."""
        self.failures: list[str] = []
        """Why each failed solve failed; the skin restarts from rest once the arm moves on."""
        self._failed_at: np.ndarray | None = None
        self.clock_origin: float | None = None
        """`time.monotonic()` (s) at which the twin's clock (`backend.time_s`, electrode drift) read 0."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @classmethod
    def for_campaign(
        cls, config: CampaignConfig, sensor_id: int, indenter: str, plant: Plant | None = None, poll_s: float = POLL_S
    ) -> TwinSources:
        """The twin of the plant sensor that a simulated campaign of `config` measures.

        plant: default `make_plant(config.sensors, config.seed)`, the one `run_campaign` draws.
        Inflates the sensor's skin (seconds).
        """
        if indenter not in config.indenters_for(sensor_id):
            raise ValueError(f"sensor {sensor_id} is not indented with {indenter!r} in this campaign")
        plant = plant if plant is not None else make_plant(list(config.sensors), config.seed)
        model, electrodes = plant_sensor_models(plant, sensor_id, make_biotac(config.mesh_max_edge))
        scene = TestbedScene(config.scene)
        rng = np.random.default_rng(np.random.SeedSequence([config.seed, sensor_id, TWIN_STREAM]))
        backend = SimBackend(
            scene,
            true_biotac_pose(plant, sensor_id, scene),
            plant.sensor(sensor_id),
            model,
            electrodes,
            plant.noise,
            rng,
            effects=plant.effects,
            joint_offsets={arm: plant.joint_offset(arm) for arm in ARMS},
        )
        return cls(backend, indenter, poll_s)

    # -- the sensors' sources (called from device threads) ---------------------------------------
    def wrench(self) -> np.ndarray:
        """(6,) F/T reading (N, N·m), sensor frame, untared: the latest published one."""
        return self._latest.wrench.copy()

    def electrodes(self) -> tuple[np.ndarray, float]:
        """((19,) electrode counts E1..E19, PDC counts): the latest published reading."""
        sample = self._latest
        return sample.electrodes.copy(), sample.pdc

    # -- following the arms -----------------------------------------------------------------------
    def home_joints(self) -> dict[str, np.ndarray]:
        """arm -> (7,) rad: the scene's parking pose, where the simulated arms should start."""
        return {arm: self.backend.scene.home_joints(arm) for arm in ARMS}

    def follow(self, arms: Mapping[str, Arm]) -> None:
        """Start the thread that keeps the twin in step with `arms` (their `.joints`, rad)."""
        if self._thread is not None:
            raise RuntimeError("the twin already follows arms")
        self.clock_origin = time.monotonic()
        self._thread = threading.Thread(target=self._run, args=(arms,), name="twin-sources", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop following (waits for a running solve to end); safe to call twice."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=30.0)

    def _run(self, arms: Mapping[str, Arm]) -> None:
        last = self.clock_origin
        while not self._stop.wait(self.poll_s):
            now = time.monotonic()
            self.step({arm: arms[arm].joints for arm in ARMS}, now - last)
            last = now

    def step(self, joints: Mapping[str, np.ndarray], dt: float) -> None:
        """Put the arms at `joints` (rad), let `dt` s pass (solving the skin there), publish a reading."""
        self._choose_arm(joints)
        for arm in ARMS:
            self.backend.command_joints(arm, joints[arm])
        start = time.monotonic()
        try:
            self.backend.advance(dt)
        except BackendError as exc:  # the readings hold (the stepper stays stopped) until the arm moves on
            if self._failed_at is None:
                self.failures.append(str(exc))
                self._failed_at = np.array(joints[self._active])
        end = time.monotonic()
        for _, result in self.backend.solve_log:  # emptied each poll: a server runs for hours
            self.solves.append(Solve(start, end, result.newton_iterations > 0))
        self.backend.solve_log.clear()
        self._latest = self.backend.read()
        self.stats["polls"] += 1

    def _choose_arm(self, joints: Mapping[str, np.ndarray]) -> None:
        """Make the nearest arm within ENGAGE_M the indenting one; restart the skin after a failure."""
        distance = {arm: self._tip_distance(arm, joints[arm]) for arm in ARMS}
        nearest = min(ARMS, key=distance.__getitem__)
        switch = nearest != self._active and distance[nearest] < ENGAGE_M
        moved_on = self._failed_at is not None and not np.array_equal(joints[self._active], self._failed_at)
        if switch or moved_on:  # a new indenting arm, or away from a failed pose: the skin from rest
            self.stats["arm_switches"] += switch
            self._active, self._failed_at = nearest if switch else self._active, None
            self.backend.attach_tool(self._active, self.indenter)

    def _tip_distance(self, arm: str, q: np.ndarray) -> float:
        """Distance (m) from `arm`'s indenter tip at joints `q` to the BioTac frame's origin."""
        tip = forward(arm, q, self._tool_tip)[:3, 3]
        return float(np.linalg.norm(tip - self.backend.true_biotac_pose[:3, 3]))
