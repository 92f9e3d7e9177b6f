"""The sensor read-out chain: what the testbed's sensors report about an fe skin state, in one place.

The fe answer for an indenter pose is the skin displacement from the inflated reference ((V, 3) m), the
fluid gauge pressure (Pa) and the indenter's force on the skin ((3,) N) at its tip ((3,) m), all in the
`biotac` frame. A `SensorReadout` turns it into

- electrodes: (19,) raw counts of `fe.electrodes.ElectrodeModel` on the deformed skin (warm-up drift at
  `time_s`; with an rng, white noise and ADC rounding; without, the expected, unquantised counts);
- PDC: raw counts, linear in the pressure (`pdc`), or the noise-free change of a pressure change
  (`pdc_change`, the tared signal);

and `ft_load` turns the force into the (6,) wrench (N, N·m) an F/T sensor reads in its own frame.

Its users: the simulated testbed (`twin.sim_backend`), the model replays (`twin.analysis.predict`), the
environments (`twin.envs.sensing`); the fe replay of a path that the replays and `twin.view` share is
`fe.indentation.step_through`.
"""

from __future__ import annotations

import numpy as np

from fe.electrodes import ElectrodeModel, ElectrodeParameters
from fe.sensor import BioTacModel


def electrode_model(
    fe_model: BioTacModel, params: ElectrodeParameters | None = None, skin_thickness: float | None = None
) -> ElectrodeModel:
    """The electrode physics of a sensor with read-out `params` (None: nominal) on `fe_model`'s inflated skin.

    skin_thickness: m, the skin the electrodes see through (default the fe model's own).
    """
    if fe_model.reference is None:
        raise ValueError("the fe model must be inflated before its electrodes are read")
    thickness = fe_model.params.thickness if skin_thickness is None else skin_thickness
    return ElectrodeModel(fe_model.geometry, params, fe_model.reference, thickness)


class SensorReadout:
    """One BioTac's electrodes and PDC reading one fe skin.

    reference: (V, 3) m, the inflated skin the displacements are measured from (biotac frame).
    electrodes: the sensor's electrode physics on that skin (`electrode_model`).

    The relative impedance of the last displacement array read is kept (by identity): a caller that reads
    the same skin state many times (the simulated testbed, hundreds of samples between solves, where only
    drift and noise change) pays for it once. The counts are the same, bit for bit; an array once read must
    not be changed in place afterwards.
    """

    def __init__(self, reference: np.ndarray, electrodes: ElectrodeModel) -> None:
        self.reference = reference
        self.electrodes = electrodes
        self._held: tuple[np.ndarray | None, np.ndarray] = (None, electrodes.relative_impedance(reference))
        """(the displacement last read (None: the rest skin), its relative impedances (19,))."""

    @classmethod
    def of_model(cls, fe_model: BioTacModel, params: ElectrodeParameters | None = None) -> SensorReadout:
        """The read-out of a sensor with read-out `params` (None: nominal) on `fe_model`'s inflated skin."""
        return cls(fe_model.reference, electrode_model(fe_model, params))

    def relative_impedance(self, displacement: np.ndarray | None) -> np.ndarray:
        """(19,) relative electrode impedances for a skin displacement (V, 3) m (None: the rest skin)."""
        if displacement is not self._held[0]:
            vertices = self.reference if displacement is None else self.reference + displacement
            self._held = (displacement, self.electrodes.relative_impedance(vertices))
        return self._held[1]

    def relative_impedances(self, displacements: np.ndarray) -> np.ndarray:
        """(N, 19) relative electrode impedances of N skin displacements (N, V, 3) m, evaluated together (the
        same as one at a time, bit for bit; the held one is left as it was)."""
        return self.electrodes.relative_impedances(self.reference + np.asarray(displacements))

    def electrode_counts(
        self, displacement: np.ndarray | None, time_s: float = 0.0, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """(19,) raw electrode counts E1..E19 for a skin displacement (V, 3) m (None: the rest skin).

        time_s: s since power-on (drift). rng: None for the expected counts, else noise and ADC rounding.
        """
        return self.impedance_counts(self.relative_impedance(displacement), time_s, rng)

    def impedance_counts(
        self, impedance: np.ndarray, time_s: float = 0.0, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """(19,) raw electrode counts of relative electrode impedances (19,) (`relative_impedance(s)`); time_s and
        rng as in `electrode_counts`."""
        return self.electrodes.impedance_counts(impedance, time_s, rng)

    def pdc(self, pressure: float, rng: np.random.Generator | None = None) -> float:
        """Raw PDC counts for the fluid gauge pressure (Pa); rng as in `electrode_counts`."""
        return self.electrodes.pdc_counts(pressure, rng)

    def pdc_change(self, pressure_change: np.ndarray) -> np.ndarray:
        """Noise-free PDC change (counts, unclipped) of pressure changes (Pa): the tared PDC signal."""
        return self.electrodes.params.pdc_gain * pressure_change


def ft_load(force_biotac: np.ndarray, point_biotac: np.ndarray, sensor_in_biotac: np.ndarray) -> np.ndarray:
    """(..., 6) wrench (N, N·m) in the F/T sensor frame of forces (..., 3; N, biotac frame) applied at points
    (..., 3; m): one load (6,) or many (K, 6) at once.

    sensor_in_biotac: 4x4 pose of the sensor frame in the biotac frame; moments are about its origin.
    """
    rotation = sensor_in_biotac[:3, :3]
    force = np.asarray(force_biotac, dtype=float)
    moment = np.cross(np.asarray(point_biotac) - sensor_in_biotac[:3, 3], force)
    return np.concatenate([force @ rotation, moment @ rotation], axis=-1)
