"""Analytic skin deformations and synthetic campaigns (numpy + h5py): a cheap stand-in for the FE.

A smooth dent: free skin vertices move inward along their normals by ``depth * exp(-d^2 / (2 width^2))``
(d = distance to the contact point) and slide tangentially by ``shear`` times the same profile. Not
mechanics: it has the right shape (local, monotone in depth) and nothing else. Metres, biotac frame.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import h5py
import numpy as np

from assets.biotac import BioTacGeometry, make_biotac, vertex_normals
from fe.electrodes import ElectrodeModel, ElectrodeParameters


def gaussian_dent(
    geometry: BioTacGeometry,
    reference: np.ndarray,
    point: np.ndarray,
    depth: float,
    width: float = 2.0e-3,
    shear: np.ndarray | None = None,
) -> np.ndarray:
    """(V, 3) m: the reference mid-surface dented at ``point`` (3,) m by ``depth`` m (peak inward motion).

    width: m, standard deviation of the dent profile. shear: (3,) m, peak tangential displacement
    (its normal component at each vertex is removed). Anchored vertices do not move.
    """
    normals = vertex_normals(reference, geometry.skin.triangles)
    dist2 = np.sum((reference - np.asarray(point, dtype=float)) ** 2, axis=1)
    profile = np.exp(-0.5 * dist2 / width**2) * ~geometry.skin.anchored
    motion = -depth * normals
    if shear is not None:
        s = np.asarray(shear, dtype=float)
        motion = motion + s - (normals @ s)[:, None] * normals
    return reference + profile[:, None] * motion


#: Dent width (m, the profile's standard deviation) and contact stiffness (N at 1 mm depth) of each
#: indenter of assets.indenters in the synthetic campaign: roughly half the indenter's critical size.
SYNTHETIC_INDENTERS: dict[str, tuple[float, float]] = {
    "sphere_small": (1.2e-3, 0.8),
    "sphere_medium": (2.0e-3, 1.5),
    "sphere_large": (3.0e-3, 2.5),
    "cylinder_short_small": (1.5e-3, 1.2),
    "cylinder_short_medium": (2.2e-3, 1.8),
    "cylinder_long": (2.6e-3, 2.2),
    "cube": (3.5e-3, 3.0),
    "ring": (3.2e-3, 2.0),
    "texture": (2.8e-3, 2.0),
}
INCREMENT = 1e-4
"""Depth step (m) between rows of a trajectory (the 0.1 mm FE increment)."""
REST_PRESSURE = 5.0e3
"""Fluid gauge pressure (Pa) of the resting synthetic sensor."""
PRESSURE_PER_VOLUME = 4.0e11
"""Pressure rise (Pa per m^3 of dent volume) of the synthetic sensor."""
FORCE_NOISE = 0.03
"""Standard deviation (N) of the synthetic F/T noise per axis."""


@dataclass(frozen=True)
class SyntheticTrajectory:
    """One straight indentation: indenter, contact point on the outer skin (m), unit direction, depths (m)."""

    indenter: int
    point: np.ndarray
    normal: np.ndarray
    direction: np.ndarray
    depths: np.ndarray


def _plan(geometry: BioTacGeometry, names: list[str], rng: np.random.Generator) -> SyntheticTrajectory:
    """A random trajectory: ventral vertex, tilt U(0, 30 deg) about the inward normal, 0.5-2 mm deep."""
    skin = geometry.skin
    normals = vertex_normals(skin.vertices, skin.triangles)
    vertex = rng.choice(np.flatnonzero(skin.ventral))
    n = normals[vertex]
    tangent = np.cross(n, rng.normal(size=3))
    tangent /= np.linalg.norm(tangent)
    tilt = rng.uniform(0.0, np.radians(30.0))
    direction = -np.cos(tilt) * n + np.sin(tilt) * tangent
    n_steps = int(round(rng.uniform(0.5e-3, 2.0e-3) / INCREMENT))
    return SyntheticTrajectory(
        indenter=int(rng.integers(len(names))),
        point=skin.vertices[vertex] + geometry.core_gap * n,
        normal=n,
        direction=direction,
        depths=INCREMENT * np.arange(n_steps + 1),
    )


def write_synthetic_campaign(
    path: str | Path,
    n_trajectories: int,
    sensor_id: int = 1,
    seed: int = 0,
    max_edge: float = 2e-3,
    params: ElectrodeParameters | None = None,
    indenters: list[str] | None = None,
) -> Path:
    """Write a small campaign HDF5 (the subset of schema v1 that `learn` reads) from analytic dents.

    Each trajectory dents the skin at a random ventral point along a tilted direction in 0.1 mm steps;
    electrodes come from `ElectrodeModel` (params: this sensor's, default sampled from the seed), force
    grows as depth^1.5 along the direction (+ F/T noise), contact_loc is the indenter tip. Learnable,
    not mechanics: for tests and benchmarks until FE campaigns exist. Returns the path.
    """
    rng = np.random.default_rng(seed)
    geometry = make_biotac(max_edge)
    names = list(SYNTHETIC_INDENTERS) if indenters is None else list(indenters)
    params = ElectrodeParameters.sample(rng) if params is None else params
    model = ElectrodeModel(geometry, params)
    reference = geometry.skin.vertices
    rows: dict[str, list] = {k: [] for k in ("raw", "tare", "pdc", "force", "fe_force", "loc", "depth", "ind")}
    rows.update(traj=[], time=[], nodal=[], pressure=[])
    meta: dict[str, list] = {k: [] for k in ("indenter_type", "point", "direction", "angle", "first_row", "n_rows")}
    for t in range(n_trajectories):
        plan = _plan(geometry, names, rng)
        width, stiffness = SYNTHETIC_INDENTERS[names[plan.indenter]]
        inward = float(-plan.direction @ plan.normal)
        meta["first_row"].append(len(rows["raw"]))
        tare = None
        for depth in plan.depths:
            shear = depth * (plan.direction + inward * plan.normal)
            deformed = gaussian_dent(geometry, reference, plan.point, depth * inward, width, shear)
            pressure = REST_PRESSURE + PRESSURE_PER_VOLUME * depth * inward * 2.0 * np.pi * width**2
            raw = model.counts(deformed, time_s=float(len(rows["raw"])), rng=rng)
            tare = raw if tare is None else tare
            fe_force = stiffness * (depth / 1e-3) ** 1.5 * plan.direction
            rows["raw"].append(raw)
            rows["tare"].append(tare)
            rows["pdc"].append(model.pdc_counts(pressure, rng=rng))
            rows["pressure"].append(pressure)
            rows["fe_force"].append(fe_force)
            rows["force"].append(fe_force + rng.normal(0.0, FORCE_NOISE, 3))
            rows["loc"].append(plan.point + depth * plan.direction)
            rows["depth"].append(depth)
            rows["ind"].append(plan.indenter)
            rows["traj"].append(t)
            rows["time"].append(float(len(rows["time"])))
            rows["nodal"].append(deformed - reference)
        meta["indenter_type"].append(plan.indenter)
        meta["point"].append(plan.point)
        meta["direction"].append(plan.direction)
        meta["angle"].append(np.arccos(np.clip(-plan.direction @ plan.normal, -1.0, 1.0)))
        meta["n_rows"].append(len(plan.depths))
    raw, tare = np.asarray(rows["raw"]), np.asarray(rows["tare"])
    features = {
        "electrode_vals": (raw - tare, "counts", None),
        "electrode_tare": (tare, "counts", None),
        "pdc": (np.asarray(rows["pdc"]), "counts", None),
        "force": (np.asarray(rows["force"]), "N", "biotac"),
        "contact_loc": (np.asarray(rows["loc"]), "m", "biotac"),
        "depth": (np.asarray(rows["depth"]), "m", None),
        "indenter_type": (np.asarray(rows["ind"], dtype=np.int64), "1", None),
        "trajectory_id": (np.asarray(rows["traj"], dtype=np.int64), "1", None),
        "time": (np.asarray(rows["time"]), "s", None),
        "nodal_res": (np.asarray(rows["nodal"]), "m", "biotac"),
        "fe_force": (np.asarray(rows["fe_force"]), "N", "biotac"),
        "fe_pressure": (np.asarray(rows["pressure"]), "Pa", None),
        "fe_converged": (np.ones(len(raw), dtype=bool), "1", None),
    }
    provenance = {
        "generator": "learn.synthetic.write_synthetic_campaign",
        "seed": seed,
        "max_edge": max_edge,
        "electrode_parameters": params.to_dict(),
        "note": "analytic Gaussian dents, not FE",
    }
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with h5py.File(tmp, "w") as f:
        f.attrs.update(
            schema_version=1,
            sensor_id=sensor_id,
            producer="biotac-twin learn.synthetic",
            provenance=json.dumps(provenance),
            created_utc=datetime.now(UTC).isoformat(),
            indenter_names=json.dumps(names),
        )
        for name, (data, units, frame) in features.items():
            ds = f.create_dataset(f"{name}/data", data=data)
            ds.attrs["units"] = units
            if frame is not None:
                ds.attrs["frame"] = frame
        f["mesh/vertices"] = reference
        f["mesh/triangles"] = geometry.skin.triangles
        f["mesh/ventral"] = geometry.skin.ventral
        traj = f.create_group("trajectories")
        traj["trajectory_id"] = np.arange(n_trajectories, dtype=np.int64)
        for key, values in meta.items():
            traj[key] = np.asarray(values)
        traj["complete"] = np.ones(n_trajectories, dtype=bool)
    tmp.replace(path)
    return path
