"""What a real BioTac (and, optionally, a wrist F/T sensor) reports about an FE state.

Electrodes and PDC come from the twin's sensor read-out (`twin.readout.SensorReadout`) of the FE's inflated
skin (nominal read-out unless parameters are given), with the ADC's noise and rounding; both are tared at the start
of each episode as a user of the real sensor would. The optional F/T reading is the FE indenter force
plus white noise. Units: counts for electrodes and PDC, N (biotac frame) for the force.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fe.electrodes import ElectrodeParameters
from twin.envs.fe_batch import IndentationBatch
from twin.readout import SensorReadout


@dataclass(frozen=True)
class Reading:
    """One raw (untared) sample: electrodes (19,) counts, PDC counts, force (3,) N in the biotac frame."""

    electrodes: np.ndarray
    pdc: float
    force: np.ndarray


class TactileReadout:
    """Turns a slot's FE state into sensor readings; shared by every slot of one `IndentationBatch`."""

    def __init__(
        self, fe: IndentationBatch, params: ElectrodeParameters | None = None, force_noise_n: float = 0.01
    ) -> None:
        if force_noise_n < 0.0:
            raise ValueError(f"force_noise_n must be >= 0 N, got {force_noise_n!r}")
        self.sensor = SensorReadout.of_model(fe.model, params)
        self.electrode_positions = fe.model.geometry.electrodes.positions
        """(19, 3) electrode centres on the core (m, biotac frame)."""
        self.force_noise_n = float(force_noise_n)

    def read(
        self,
        displacement: np.ndarray,
        pressure: float,
        force: np.ndarray,
        rng: np.random.Generator,
        impedance: np.ndarray | None = None,
    ) -> Reading:
        """Noisy sensor readings for a skin displacement (V, 3) m, fluid pressure (Pa) and indenter force (3,) N;
        `impedance`: that skin's relative electrode impedances (19,) when already evaluated (with other skins':
        `SensorReadout.relative_impedances`)."""
        if impedance is None:
            impedance = self.sensor.relative_impedance(displacement)
        electrodes = self.sensor.impedance_counts(impedance, 0.0, rng)
        pdc = self.sensor.pdc(pressure, rng)
        noisy_force = np.asarray(force, dtype=float) + self.force_noise_n * rng.standard_normal(3)
        return Reading(electrodes, pdc, noisy_force)
