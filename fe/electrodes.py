"""Physics-based BioTac electrode model: fluid-film impedance to 12-bit counts (numpy only, no torch).

Frames and units: the ``biotac`` frame of the product manual (x distal, -z ventral), metres, pascals,
seconds; outputs are raw ADC counts (0..4095).

Physics. Each electrode sits on the rigid core under a film of conductive fluid that ends at the inner
surface of the skin. Current leaves the electrode and spreads through that film, so the electrode's
impedance is a series sum over the film it sees: ``Z_e ~ rho * mean_w(1 / h)``, where ``h`` is the local
film thickness measured along the electrode normal from the electrode to the deformed inner skin
surface, and ``mean_w`` is an area-weighted mean with a compact footprint kernel
``w(l) = (1 - l^2 / R^2)^2`` of the lateral distance ``l`` from the electrode axis (``R`` =
``footprint_radius``). Where the skin approaches, ``h`` falls, ``Z_e`` rises. Relative to the resting
(reference) skin, ``z_e = Z_e / Z_e,rest``.

Read-out. The electrode impedance forms a voltage divider with a load impedance ``Z_L``; the ADC reads
``V ~ 1 / (1 + lambda z_e)`` with ``lambda = Z_e,rest / Z_L`` (``load_ratio``). With the per-sensor
amplifier ``gain`` and resting ``offset``::

    counts_e = offset_e + gain_e * 4095 * (1 / (1 + lambda_e z_e) - 1 / (1 + lambda_e)) + drift_e(t) + noise

so counts equal ``offset`` at the reference skin and go down where the skin approaches (facts). Drift is a
warm-up exponential ``A_e (1 - exp(-t / tau))``. The PDC channel is linear in the fluid gauge pressure:
``pdc = pdc_offset + pdc_gain * p``. Both are clipped to the 12-bit range. With ``rng=None`` the model
returns the expected, unquantised counts (smooth, for fitting); with an ``rng`` it adds Gaussian noise and
rounds to integer counts (the ADC).

Resting counts, gains and sensitivities of real sensors are *unverified* (facts/biotac.md): every
number here is a parameter with a documented default.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np
from scipy import sparse

from assets.biotac import BioTacGeometry, Electrodes, electrode_table
from fe.shell import lumped_areas

N_ELECTRODES = 19
ADC_MAX = 4095.0
"""Largest 12-bit count."""
DEFAULT_SKIN_THICKNESS = 1.57e-3
"""Skin thickness (m) when a bare mesh gives none: the paper's calibrated optimum."""
PDC_FULL_SCALE_PA = 100e3
"""Gauge pressure (Pa) at the top of the PDC range (facts: 0-100 kPa over 12 bits)."""


def _per_electrode(value: float) -> np.ndarray:
    return np.full(N_ELECTRODES, float(value))


@dataclass(frozen=True)
class ElectrodeParameters:
    """Read-out parameters of one physical BioTac (per-electrode arrays are (19,), E1..E19).

    offset: counts at the reference (resting) skin; facts: 2100-3700 plausible, *unverified*.
    gain: amplifier gain of the divider signal (1 = the divider spans the full 12-bit range).
    load_ratio: lambda = resting electrode impedance / load impedance (dimensionless, > 0).
    drift_amplitude: warm-up drift reached after a few time constants (counts).
    drift_time_constant: warm-up time constant (s, > 0).
    noise_std: standard deviation of white electrode noise (counts).
    footprint_radius: radius R (m) of the skin patch an electrode sees (kernel support).
    min_gap: floor (m) of the local film thickness, the skin's roughness when it touches the core.
    pdc_offset: PDC counts at zero gauge pressure.
    pdc_gain: PDC counts per pascal of gauge pressure.
    pdc_noise_std: standard deviation of PDC noise (counts).
    """

    offset: np.ndarray = field(default_factory=lambda: _per_electrode(2900.0))
    gain: np.ndarray = field(default_factory=lambda: _per_electrode(1.0))
    load_ratio: np.ndarray = field(default_factory=lambda: _per_electrode(1.0))
    drift_amplitude: np.ndarray = field(default_factory=lambda: _per_electrode(0.0))
    drift_time_constant: float = 300.0
    noise_std: float = 3.0
    footprint_radius: float = 3.0e-3
    min_gap: float = 0.02e-3
    pdc_offset: float = 0.0
    pdc_gain: float = ADC_MAX / PDC_FULL_SCALE_PA
    pdc_noise_std: float = 1.0

    def __post_init__(self) -> None:
        for name in ("offset", "gain", "load_ratio", "drift_amplitude"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (N_ELECTRODES,) or not np.all(np.isfinite(value)):
                raise ValueError(f"ElectrodeParameters.{name} must be 19 finite values, got shape {value.shape}")
            object.__setattr__(self, name, value)
        for name in ("gain", "load_ratio", "drift_time_constant", "footprint_radius", "min_gap", "pdc_gain"):
            if not np.all(np.asarray(getattr(self, name)) > 0.0):
                raise ValueError(f"ElectrodeParameters.{name} must be > 0, got {getattr(self, name)!r}")
        for name in ("noise_std", "pdc_noise_std"):
            if not getattr(self, name) >= 0.0:
                raise ValueError(f"ElectrodeParameters.{name} must be >= 0, got {getattr(self, name)!r}")
        if self.footprint_radius > 0.02:
            raise ValueError(f"footprint_radius {self.footprint_radius!r} m is not a BioTac length (metres?)")

    @classmethod
    def sample(cls, rng: np.random.Generator) -> ElectrodeParameters:
        """A random, plausible sensor: the unit-to-unit spread the paper reports, as priors.

        offset U(2100, 3700) counts; gain and load_ratio log-normal (sigma 0.25) about 1; drift
        amplitude N(0, 30) counts with a time constant U(60, 600) s; noise U(2, 6) counts; footprint
        radius U(2.5, 3.5) mm; PDC offset U(0, 100) counts, gain 5 % about nominal. All *unverified*.
        """
        return cls(
            offset=rng.uniform(2100.0, 3700.0, N_ELECTRODES),
            gain=rng.lognormal(0.0, 0.25, N_ELECTRODES),
            load_ratio=rng.lognormal(0.0, 0.25, N_ELECTRODES),
            drift_amplitude=rng.normal(0.0, 30.0, N_ELECTRODES),
            drift_time_constant=float(rng.uniform(60.0, 600.0)),
            noise_std=float(rng.uniform(2.0, 6.0)),
            footprint_radius=float(rng.uniform(2.5e-3, 3.5e-3)),
            pdc_offset=float(rng.uniform(0.0, 100.0)),
            pdc_gain=float(ADC_MAX / PDC_FULL_SCALE_PA * rng.normal(1.0, 0.05)),
        )

    def to_dict(self) -> dict[str, float | list[float]]:
        """JSON-ready copy (arrays as lists), for provenance records."""
        out: dict[str, float | list[float]] = {}
        for f in fields(self):
            value = getattr(self, f.name)
            out[f.name] = value.tolist() if isinstance(value, np.ndarray) else float(value)
        return out


class ElectrodeModel:
    """The 19 electrodes of one sensor, reading a deformed skin mesh.

    geometry: the BioTac geometry whose skin mesh the vertices belong to (electrode positions/normals,
        triangles; `from_mesh` takes bare arrays instead). params: this sensor's read-out parameters.
    reference: (V, 3) m, resting mid-surface (usually the FE's inflated state) at which the counts
        equal ``params.offset``; default the geometry's unpressurised skin.
    skin_thickness: m, skin thickness; the inner skin surface is the mid-surface offset inward by half
        of it along the vertex normals; default twice ``geometry.core_gap``.

    The skin patch each electrode sees is fixed at construction (vertices within the footprint radius
    plus a 2 mm sliding margin of the electrode axis, on the electrode's side), so a call costs
    O(patch size).
    """

    SLIDE_MARGIN = 2.0e-3
    """Extra lateral distance (m) kept around each footprint so skin that slides in is still seen."""
    CHUNK_TRIANGLES = 16384
    """`impedances` evaluates skins in chunks of about this many skin triangles (all skins' together), which
    keeps its temporaries in cache: 2.8x faster than one skin at a time, where one pass over a thousand is
    slower (2 mm mesh, 32 skins a chunk)."""

    def __init__(
        self,
        geometry: BioTacGeometry,
        params: ElectrodeParameters | None = None,
        reference: np.ndarray | None = None,
        skin_thickness: float | None = None,
    ) -> None:
        self._setup(
            geometry.skin.vertices if reference is None else reference,
            geometry.skin.triangles,
            geometry.electrodes,
            2.0 * geometry.core_gap if skin_thickness is None else skin_thickness,
            params,
        )

    @classmethod
    def from_mesh(
        cls,
        reference: np.ndarray,
        triangles: np.ndarray,
        params: ElectrodeParameters | None = None,
        skin_thickness: float = DEFAULT_SKIN_THICKNESS,
        electrodes: Electrodes | None = None,
    ) -> ElectrodeModel:
        """The model on a bare skin mesh (e.g. a campaign file's ``mesh/vertices``, ``mesh/triangles``):
        reference (V, 3) m, triangles (T, 3) oriented away from the core; electrodes default to the
        product manual's table."""
        model = cls.__new__(cls)
        model._setup(
            reference, triangles, electrode_table() if electrodes is None else electrodes, skin_thickness, params
        )
        return model

    def _setup(
        self,
        reference: np.ndarray,
        triangles: np.ndarray,
        electrodes: Electrodes,
        skin_thickness: float,
        params: ElectrodeParameters | None,
    ) -> None:
        self.params = params if params is not None else ElectrodeParameters()
        self.skin_thickness = float(skin_thickness)
        if not 0.0 < self.skin_thickness < 0.01:
            raise ValueError(f"skin_thickness must be in (0, 0.01) m, got {self.skin_thickness!r}")
        self.reference = np.array(reference, dtype=float)
        if self.reference.ndim != 2 or self.reference.shape[1] != 3 or not np.all(np.isfinite(self.reference)):
            raise ValueError(f"reference must be finite (V, 3) m, got shape {self.reference.shape}")
        self._triangles = np.asarray(triangles)
        if self._triangles.ndim != 2 or self._triangles.shape[1] != 3 or self._triangles.max() >= len(self.reference):
            raise ValueError(f"triangles must be (T, 3) ids into the {len(self.reference)} reference vertices")
        self._positions = electrodes.positions
        self._normals = electrodes.normals
        self._patches = self._select_patches()
        self._index_patches()
        self._areas = lumped_areas(self.reference, self._triangles)
        self._rest_impedance = self.impedance(self.reference)
        if not np.all(np.isfinite(self._rest_impedance)):
            raise ValueError("an electrode sees no skin at the reference state (check the geometry/reference)")

    def _select_patches(self) -> list[np.ndarray]:
        """For each electrode, the skin vertex ids it may see: in front of it, near its axis."""
        reach = self.params.footprint_radius + self.SLIDE_MARGIN
        patches = []
        for p, n in zip(self._positions, self._normals, strict=True):
            rel = self.reference - p
            along = rel @ n
            lateral = np.linalg.norm(rel - along[:, None] * n, axis=1)
            ids = np.flatnonzero((along > 0.0) & (lateral < reach))
            if len(ids) == 0:
                raise ValueError(f"no skin vertex in front of electrode at {np.round(p * 1e3, 2)} mm")
            patches.append(ids)
        return patches

    def _index_patches(self) -> None:
        """Flatten the patches for vectorised evaluation and restrict the normal computation to the
        vertices they hold: a sparse (used vertex x adjacent triangle) incidence matrix."""
        self._used = np.unique(np.concatenate(self._patches))
        local = np.full(len(self.reference), -1)
        local[self._used] = np.arange(len(self._used))
        self._entry_vertex = np.concatenate(self._patches)  # global vertex id of each (electrode, vertex)
        self._entry_local = local[self._entry_vertex]
        self._entry_electrode = np.repeat(np.arange(N_ELECTRODES), [len(p) for p in self._patches])
        touching = np.flatnonzero((local[self._triangles] >= 0).any(axis=1))
        self._near_triangles = self._triangles[touching]
        rows = local[self._near_triangles].ravel()
        cols = np.repeat(np.arange(len(touching)), 3)
        keep = rows >= 0
        self._incidence = sparse.csr_matrix(
            (np.ones(keep.sum()), (rows[keep], cols[keep])), shape=(len(self._used), len(touching))
        )

    def impedance(self, vertices: np.ndarray) -> np.ndarray:
        """(19,) film impedance of each electrode up to the constant rho: mean_w(1 / h), 1/m.

        vertices: (V, 3) m, deformed skin mid-surface, biotac frame. An electrode whose footprint holds
        no skin (all slid away) gets inf.
        """
        return self.impedances(np.asarray(vertices, dtype=float)[None])[0]

    def impedances(self, vertices: np.ndarray) -> np.ndarray:
        """(N, 19) `impedance` of N skins at once, vertices (N, V, 3) m (each skin's the same, bit for bit, as
        one at a time)."""
        vertices, expected = np.asarray(vertices, dtype=float), self.reference.shape
        if vertices.ndim != 3 or vertices.shape[1:] != expected or not np.all(np.isfinite(vertices)):
            raise ValueError(f"vertices must be finite with shape {expected} (m), got {vertices.shape[1:]}")
        chunk = max(1, self.CHUNK_TRIANGLES // len(self._near_triangles))
        return np.concatenate([self._impedances(vertices[k : k + chunk]) for k in range(0, len(vertices), chunk)])

    def _impedances(self, vertices: np.ndarray) -> np.ndarray:
        """`impedances` of checked vertices (N, V, 3) m in one vectorised pass."""
        n, p = len(vertices), vertices[:, self._near_triangles]
        cross = np.cross(p[:, :, 1] - p[:, :, 0], p[:, :, 2] - p[:, :, 0])  # (N, T, 3), area-weighted normals
        normals = (self._incidence @ cross.transpose(1, 0, 2).reshape(-1, 3 * n)).reshape(-1, n, 3).transpose(1, 0, 2)
        normals = normals / np.linalg.norm(normals, axis=2, keepdims=True)
        inner = vertices[:, self._used] - 0.5 * self.skin_thickness * normals
        e = self._entry_electrode
        rel = inner[:, self._entry_local] - self._positions[e]
        along = np.einsum("nij,ij->ni", rel, self._normals[e])
        lateral2 = np.einsum("nij,nij->ni", rel, rel) - along**2
        radius = self.params.footprint_radius
        weight = self._areas[self._entry_vertex] * np.clip(1.0 - lateral2 / radius**2, 0.0, None) ** 2
        gap = np.maximum(along, self.params.min_gap)
        bins = (np.arange(n)[:, None] * N_ELECTRODES + e).ravel()
        total = np.bincount(bins, weights=weight.ravel(), minlength=n * N_ELECTRODES).reshape(n, N_ELECTRODES)
        series = np.bincount(bins, weights=(weight / gap).ravel(), minlength=n * N_ELECTRODES)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(total > 0.0, series.reshape(n, N_ELECTRODES) / total, np.inf)

    def relative_impedance(self, vertices: np.ndarray) -> np.ndarray:
        """(19,) z_e = Z_e / Z_e,rest (1 at the reference skin, > 1 where the skin approaches)."""
        return self.impedance(vertices) / self._rest_impedance

    def relative_impedances(self, vertices: np.ndarray) -> np.ndarray:
        """(N, 19) `relative_impedance` of N skins at once, vertices (N, V, 3) m."""
        return self.impedances(vertices) / self._rest_impedance

    def drift(self, time_s: float) -> np.ndarray:
        """(19,) warm-up drift (counts) at time_s (s) since power-on."""
        if time_s < 0.0:
            raise ValueError(f"time_s must be >= 0, got {time_s!r}")
        return self.params.drift_amplitude * -np.expm1(-time_s / self.params.drift_time_constant)

    def counts(self, vertices: np.ndarray, time_s: float = 0.0, rng: np.random.Generator | None = None) -> np.ndarray:
        """(19,) raw electrode counts E1..E19 for the deformed mid-surface vertices (V, 3) m.

        time_s: seconds since power-on (drift). rng: None for the expected, unquantised counts; a
        generator adds white noise and rounds to integers. Always clipped to 0..4095.
        """
        return self.impedance_counts(self.relative_impedance(vertices), time_s, rng)

    def impedance_counts(
        self, z: np.ndarray, time_s: float = 0.0, rng: np.random.Generator | None = None
    ) -> np.ndarray:
        """(19,) raw electrode counts for the relative impedances z (19,) (`relative_impedance`); time_s and rng
        as in `counts`."""
        p = self.params
        lam = p.load_ratio
        signal = p.gain * ADC_MAX * (1.0 / (1.0 + lam * z) - 1.0 / (1.0 + lam))
        value = p.offset + signal + self.drift(time_s)
        if rng is not None:
            value = np.rint(value + rng.normal(0.0, p.noise_std, N_ELECTRODES))
        return np.clip(value, 0.0, ADC_MAX)

    def pdc_counts(self, pressure: float, rng: np.random.Generator | None = None) -> float:
        """Raw PDC counts for the fluid gauge pressure (Pa); noise and rounding as in ``counts``."""
        if not np.isfinite(pressure):
            raise ValueError(f"pressure must be finite (Pa), got {pressure!r}")
        value = self.params.pdc_offset + self.params.pdc_gain * pressure
        if rng is not None:
            value = np.rint(value + rng.normal(0.0, self.params.pdc_noise_std))
        return float(np.clip(value, 0.0, ADC_MAX))
