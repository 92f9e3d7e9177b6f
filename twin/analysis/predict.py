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
from dataclasses import asdict, dataclass, field

import numpy as np

from assets.biotac import make_biotac
from fe.params import SkinParameters
from fe.sensor import BioTacModel
from learn.electrode_physics import ElectrodeModel
from twin.analysis.data import TrajectoryRecord
from twin.controller import Recording
from twin.effects import EffectValues, apply_path, apply_skin, check_values, measure_wrench
from twin.processing import ProcessedRows, lowpass, process
from twin.sim_backend import ft_load


@dataclass(frozen=True)
class TwinModel:
    """What predicts: nominal skin parameters, effect values, fe mesh size (m)."""

    skin: SkinParameters = field(default_factory=SkinParameters)
    effects: EffectValues = field(default_factory=dict)
    mesh_max_edge: float = 2e-3

    def __post_init__(self) -> None:
        check_values(self.effects)

    def with_effects(self, effects: EffectValues) -> TwinModel:
        """The same model with `effects` merged over its own (per effect, per parameter)."""
        merged = {k: dict(v) for k, v in self.effects.items()}
        for name, values in effects.items():
            merged.setdefault(name, {}).update(values)
        return TwinModel(self.skin, merged, self.mesh_max_edge)

    def to_dict(self) -> dict:
        """JSON-ready description."""
        return {"skin": asdict(self.skin), "effects": self.effects, "mesh_max_edge": self.mesh_max_edge}

    @classmethod
    def from_dict(cls, data: dict) -> TwinModel:
        """Inverse of `to_dict`."""
        return cls(SkinParameters(**data["skin"]), data.get("effects", {}), float(data["mesh_max_edge"]))

    def key(self) -> str:
        """Stable hash of the model."""
        return hashlib.sha256(json.dumps(self.to_dict(), sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Prediction:
    """A model's view of one trajectory: per-increment fe results, full-rate signals and rows."""

    increment_force: np.ndarray  # (K, 3) N, biotac frame, fe force of each path index
    increment_pressure: np.ndarray  # (K,) Pa
    converged: np.ndarray  # (K,) bool; later indices after a failure are NaN-filled
    force_fullrate: np.ndarray  # (T, 3) N, biotac frame, tared, unfiltered (model + measurement effects)
    rows: ProcessedRows


class Predictor:
    """Replays trajectories; inflated fe models and fe replays are cached.

    A replay depends only on the skin parameters, the mesh and the indenter path, so predictions that
    differ only in measurement effects reuse it.
    """

    def __init__(self) -> None:
        self._models: dict[tuple, BioTacModel] = {}
        self._electrodes: dict[int, ElectrodeModel] = {}
        self._replays: dict[tuple, tuple] = {}

    def fe_model(self, skin: SkinParameters, mesh_max_edge: float) -> BioTacModel:
        """An inflated fe model for these parameters (built once)."""
        key = (tuple(sorted(asdict(skin).items())), mesh_max_edge)
        if key not in self._models:
            model = BioTacModel(make_biotac(mesh_max_edge), skin)
            result = model.inflate()
            if not result.converged:
                raise RuntimeError(f"the model did not inflate for {skin}: {result.message}")
            self._models[key] = model
        return self._models[key]

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
        key = (tuple(sorted(asdict(skin).items())), model.mesh_max_edge, trajectory.sensor_id)
        key += (trajectory.trajectory_id, tips.round(12).tobytes())
        if key not in self._replays:
            fe = self.fe_model(skin, model.mesh_max_edge)
            self._replays[key] = _replay(fe, self.electrode_model(fe), trajectory, tips)
        forces, pressures, converged, electrodes = self._replays[key]
        index = raw.increment + 1  # path index of every sample
        loads = np.array([ft_load(f, t, trajectory.sensor_in_biotac) for f, t in zip(forces, tips, strict=True)])
        times = raw.time

        def clean_at(t: np.ndarray) -> np.ndarray:
            k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 1)
            return loads[index[k]]

        wrench = measure_wrench(times, clean_at, model.effects)
        pdc = raw.pdc[0] + _PDC_COUNTS_PER_PA * (pressures[index] - pressures[0])
        predicted = Recording(
            time=times,
            joints=raw.joints,
            wrench=wrench,
            electrodes=raw.electrodes[0] + electrodes[index] - electrodes[0],
            pdc=pdc,
            depth_command=raw.depth_command,
            increment=raw.increment,
            complete=bool(converged.all()),
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
        return Prediction(forces, pressures, converged, tared, rows)


_PDC_COUNTS_PER_PA = 4095.0 / 100e3
"""Nominal PDC scale: 12 bits over 0-100 kPa (facts: BioTac signals table)."""


def _path_depths(raw: Recording) -> np.ndarray:
    """Commanded depth of each path index (-1 standoff first), from the recording's labels."""
    n = int(raw.increment.max()) + 2
    depths = np.full(n, np.nan)
    depths[raw.increment + 1] = raw.depth_command
    return depths


def _replay(fe: BioTacModel, electrode_model: ElectrodeModel, trajectory: TrajectoryRecord, tips: np.ndarray) -> tuple:
    """Per path index: fe force (N), pressure (Pa), converged flag, electrode counts (nan after a failure)."""
    stepper = fe.stepper(trajectory.indenter)
    forces = np.full((len(tips), 3), np.nan)
    pressures = np.full(len(tips), np.nan)
    electrodes = np.full((len(tips), 19), np.nan)
    converged = np.zeros(len(tips), dtype=bool)
    for k, tip in enumerate(tips):
        result = stepper.step(trajectory.rotation, tip)
        if not result.converged:
            break
        forces[k], pressures[k], converged[k] = result.force, result.pressure, True
        electrodes[k] = electrode_model.counts(fe.reference + result.displacement)
    return forces, pressures, converged, electrodes


def measured_force_fullrate(trajectory: TrajectoryRecord) -> np.ndarray:
    """(T, 3) measured force on the BioTac (N, biotac frame), tared, unfiltered."""
    wrench = trajectory.raw.wrench
    return (wrench[:, :3] - wrench[0, :3]) @ trajectory.sensor_in_biotac[:3, :3].T


def filtered(force: np.ndarray, rate_hz: float) -> np.ndarray:
    """The paper's force filter applied to a full-rate series."""
    return lowpass(force, rate_hz)
