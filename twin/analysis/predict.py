"""Model predictions of measured trajectories: replay each path through fe and the measurement chain.

A `TwinModel` is the nominal skin parameters plus effect values (twin.effects) and a mesh size. The
prediction of a trajectory re-solves the skin along the trajectory's recorded path (standoff,
loading, unloading: the same pose sequence the testbed ran), turns each increment's force into the
F/T load the mount sees, runs it through the model's measurement effects at the recorded sample
times, and then through the very processing the measurements went through (tare, 5 Hz zero-phase
low-pass, increment-end subsampling), so predicted and measured rows are directly comparable.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from assets.biotac import make_biotac
from fe.params import SkinParameters
from fe.sensor import SENSOR_THICKNESS, BioTacModel, InflationResult
from learn.electrode_physics import ElectrodeModel
from twin.analysis.data import TrajectoryRecord
from twin.controller import Recording
from twin.effects import EffectValues, apply_path, apply_skin, check_values, measure_wrench
from twin.processing import ProcessedRows, lowpass, process
from twin.sim_backend import RELAXATION_SOLVE_INTERVAL_S, ft_load

INFLATION_RULES = ("thickness", "thermal")
"""How a model's skin is inflated (see TwinModel)."""
MODEL_CACHE_SIZE = 24
"""Inflated fe models a Predictor keeps (first built dropped first); replays, small arrays, are all kept."""


@dataclass(frozen=True)
class TwinModel:
    """What predicts: nominal skin parameters, effect values, fe mesh size (m) and how the skin is
    inflated: "thickness" (fill until the sensor is 15.1 mm thick, the twin's default) or "thermal" (the
    paper's rule: the fluid expands from the reference to `skin.fluid_temperature`)."""

    skin: SkinParameters = field(default_factory=SkinParameters)
    effects: EffectValues = field(default_factory=dict)
    mesh_max_edge: float = 2e-3
    inflation: str = "thickness"

    def __post_init__(self) -> None:
        check_values(self.effects)
        if self.inflation not in INFLATION_RULES:
            raise ValueError(f"inflation must be one of {INFLATION_RULES}, got {self.inflation!r}")

    def with_effects(self, effects: EffectValues) -> TwinModel:
        """The same model with `effects` merged over its own (per effect, per parameter)."""
        merged = {k: dict(v) for k, v in self.effects.items()}
        for name, values in effects.items():
            merged.setdefault(name, {}).update(values)
        return replace(self, effects=merged)

    def to_dict(self) -> dict:
        """JSON-ready description."""
        return {
            "skin": asdict(self.skin),
            "effects": self.effects,
            "mesh_max_edge": self.mesh_max_edge,
            "inflation": self.inflation,
        }

    @classmethod
    def from_dict(cls, data: dict) -> TwinModel:
        """Inverse of `to_dict`."""
        return cls(
            SkinParameters(**data["skin"]),
            data.get("effects", {}),
            float(data["mesh_max_edge"]),
            data.get("inflation", "thickness"),
        )

    def key(self) -> str:
        """Stable hash of the model."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


def inflated_fe_model(
    skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness"
) -> tuple[BioTacModel, InflationResult]:
    """A BioTac fe model of `skin` meshed at `mesh_max_edge` (m) and inflated by the rule `inflation` (see
    TwinModel), with its InflationResult (which says whether it converged)."""
    model = BioTacModel(make_biotac(mesh_max_edge), skin)
    return model, model.inflate(SENSOR_THICKNESS if inflation == "thickness" else None)


@dataclass(frozen=True)
class Prediction:
    """A model's view of one trajectory: per-increment fe results, full-rate signals and rows."""

    increment_force: np.ndarray  # (K, 3) N, biotac frame, fe force of each path index
    increment_pressure: np.ndarray  # (K,) Pa
    converged: np.ndarray  # (K,) bool; later indices after a failure are NaN-filled
    force_fullrate: np.ndarray  # (T, 3) N, biotac frame, tared, unfiltered (model + measurement effects)
    pdc_fullrate: np.ndarray  # (T,) counts, tared: the nominal PDC read-out of the pressure change
    rows: ProcessedRows


class Predictor:
    """Replays trajectories; inflated fe models and fe replays are cached.

    A replay depends only on the skin parameters, the mesh and the indenter path, so predictions that
    differ only in measurement effects reuse it.
    """

    def __init__(self) -> None:
        self._models: dict[tuple, tuple[BioTacModel, InflationResult]] = {}
        self._electrodes: dict[int, ElectrodeModel] = {}
        self._replays: dict[tuple, Replay] = {}

    def inflated(self, skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness") -> tuple:
        """(fe model, its InflationResult) for these parameters, inflated by `inflation` (built once)."""
        key = (tuple(sorted(asdict(skin).items())), mesh_max_edge, inflation)
        if key not in self._models:
            model, result = inflated_fe_model(skin, mesh_max_edge, inflation)
            if not result.converged:
                raise RuntimeError(f"the model did not inflate for {skin}: {result.message}")
            if len(self._models) >= MODEL_CACHE_SIZE:
                dropped = next(iter(self._models))
                self._electrodes.pop(id(self._models.pop(dropped)[0]), None)
            self._models[key] = (model, result)
        return self._models[key]

    def fe_model(self, skin: SkinParameters, mesh_max_edge: float, inflation: str = "thickness") -> BioTacModel:
        """An inflated fe model for these parameters (built once)."""
        return self.inflated(skin, mesh_max_edge, inflation)[0]

    def electrode_model(self, fe: BioTacModel) -> ElectrodeModel:
        """Nominal electrode physics on this fe model's inflated skin (read-out gains unknown: nominal)."""
        key = id(fe)
        if key not in self._electrodes:
            self._electrodes[key] = ElectrodeModel(fe.geometry, None, fe.reference, fe.params.thickness)
        return self._electrodes[key]

    def predict(self, model: TwinModel, trajectory: TrajectoryRecord) -> Prediction:
        """The model's prediction of `trajectory` (see the module docstring)."""
        skin = apply_skin(model.skin, model.effects)
        raw = trajectory.raw
        path_depths = _path_depths(raw)
        tips = apply_path(trajectory.touch_point + np.outer(path_depths, trajectory.direction), model.effects)
        timed = skin.relaxation_fraction > 0.0
        model_key = (tuple(sorted(asdict(skin).items())), model.mesh_max_edge, model.inflation)
        key = (model_key, trajectory.sensor_id, trajectory.trajectory_id, tips.round(12).tobytes())
        if key not in self._replays:
            fe = self.fe_model(skin, model.mesh_max_edge, model.inflation)
            events = solve_events(raw, RELAXATION_SOLVE_INTERVAL_S if timed else None)
            self._replays[key] = _replay(fe, self.electrode_model(fe), trajectory, tips, events, timed)
        replay = self._replays[key]
        times = raw.time
        sample_event = np.clip(np.searchsorted(replay.time, times, side="right") - 1, 0, None)
        loads = np.array(
            [
                ft_load(f, tips[k], trajectory.sensor_in_biotac)
                for f, k in zip(replay.force, replay.path_index, strict=True)
            ]
        )

        def clean_at(t: np.ndarray) -> np.ndarray:
            return loads[np.clip(np.searchsorted(replay.time, t, side="right") - 1, 0, None)]

        wrench = measure_wrench(times, clean_at, model.effects)
        pdc_change = _PDC_COUNTS_PER_PA * (replay.pressure[sample_event] - replay.pressure[0])
        pdc = raw.pdc[0] + pdc_change
        predicted = Recording(
            time=times,
            joints=raw.joints,
            wrench=wrench,
            electrodes=raw.electrodes[0] + replay.electrodes[sample_event] - replay.electrodes[0],
            pdc=pdc,
            depth_command=raw.depth_command,
            increment=raw.increment,
            complete=bool(replay.converged.all()),
            message="",
        )
        rows = process(
            predicted,
            trajectory.arm,
            trajectory.tool_tip,
            np.linalg.inv(trajectory.registration),
            trajectory.sensor_in_biotac,
            trajectory.rate_hz,
        )
        tared = (wrench[:, :3] - wrench[0, :3]) @ trajectory.sensor_in_biotac[:3, :3].T
        last = np.r_[np.flatnonzero(np.diff(replay.path_index)), len(replay.path_index) - 1]  # per path index
        return Prediction(replay.force[last], replay.pressure[last], replay.converged[last], tared, pdc_change, rows)


_PDC_COUNTS_PER_PA = 4095.0 / 100e3
"""Nominal PDC scale: 12 bits over 0-100 kPa (facts: BioTac signals table)."""


def _path_depths(raw: Recording) -> np.ndarray:
    """Commanded depth of each path index (-1 standoff first), from the recording's labels."""
    n = int(raw.increment.max()) + 2
    depths = np.full(n, np.nan)
    depths[raw.increment + 1] = raw.depth_command
    return depths


@dataclass(frozen=True)
class Replay:
    """fe solves along a trajectory's path, one per event: the event's time (s, the recording's clock),
    path index, force (N, biotac frame), pressure (Pa), electrode counts and converged flag (NaN after a
    failure)."""

    time: np.ndarray  # (S,)
    path_index: np.ndarray  # (S,)
    force: np.ndarray  # (S, 3)
    pressure: np.ndarray  # (S,)
    electrodes: np.ndarray  # (S, 19)
    converged: np.ndarray  # (S,) bool


def solve_events(raw: Recording, interval_s: float | None) -> tuple[np.ndarray, np.ndarray]:
    """(times s, path indices) at which the skin is solved: each path index when its increment starts,
    and, with `interval_s`, again every `interval_s` while the pose is held (relaxation)."""
    starts = np.r_[0, np.flatnonzero(np.diff(raw.increment)) + 1]
    ends = np.r_[raw.time[starts[1:]], raw.time[-1]]
    times, indices = [], []
    for start, end in zip(starts, ends, strict=True):
        held = [raw.time[start]]
        if interval_s is not None:
            held = np.arange(raw.time[start], end, interval_s)
        times.extend(held)
        indices.extend([raw.increment[start] + 1] * len(held))
    return np.asarray(times, dtype=float), np.asarray(indices, dtype=int)


def _replay(
    fe: BioTacModel,
    electrode_model: ElectrodeModel,
    trajectory: TrajectoryRecord,
    tips: np.ndarray,
    events: tuple[np.ndarray, np.ndarray],
    timed: bool,
) -> Replay:
    """Solve the skin at every event (see `solve_events`); stops at the first failure."""
    stepper = fe.stepper(trajectory.indenter)
    times, indices = events
    n = len(times)
    replay = Replay(
        times, indices, np.full((n, 3), np.nan), np.full(n, np.nan), np.full((n, 19), np.nan), np.zeros(n, bool)
    )
    for s, (t, k) in enumerate(zip(times, indices, strict=True)):
        result = stepper.step(trajectory.rotation, tips[k], float(t) if timed else None)
        if not result.converged:
            break
        replay.force[s], replay.pressure[s], replay.converged[s] = result.force, result.pressure, True
        replay.electrodes[s] = electrode_model.counts(fe.reference + result.displacement)
    return replay


def measured_force_fullrate(trajectory: TrajectoryRecord) -> np.ndarray:
    """(T, 3) measured force on the BioTac (N, biotac frame), tared, unfiltered."""
    wrench = trajectory.raw.wrench
    return (wrench[:, :3] - wrench[0, :3]) @ trajectory.sensor_in_biotac[:3, :3].T


def measured_pdc_fullrate(trajectory: TrajectoryRecord) -> np.ndarray:
    """(T,) measured PDC counts, tared (first sample subtracted), unfiltered."""
    pdc = np.asarray(trajectory.raw.pdc, dtype=float)
    return pdc - pdc[0]


def filtered(force: np.ndarray, rate_hz: float) -> np.ndarray:
    """The paper's force filter applied to a full-rate series."""
    return lowpass(force, rate_hz)
