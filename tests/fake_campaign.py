"""Tiny schema-complete campaign parts and files without any FE or robot (for CLI error and integrity tests)."""

from pathlib import Path

import numpy as np
import trimesh

from assets.indenters import INDENTERS
from twin.dataset import assemble_sensor_file, part_path, write_part

ROWS, SAMPLES = 4, 10
"""Subsampled rows and full-rate samples of each fake trajectory."""
SKIN = trimesh.creation.icosahedron()
"""The fake skin: an icosahedron of radius 5 mm (12 vertices)."""
VERTICES = np.asarray(SKIN.vertices) * 5e-3


def fake_part(trajectory_id: int) -> dict[str, np.ndarray]:
    """A schema-complete part of ROWS rows: a press of 0..0.3 mm along +z under a growing +z force."""
    n, m = ROWS, SAMPLES
    depth = np.linspace(0.0, 0.3e-3, n)
    rows = {
        "electrode_vals": np.outer(depth, np.ones(19)) * 1e5,
        "electrode_tare": np.full((n, 19), 2000.0),
        "pdc": 2000.0 + depth * 1e5,
        "force": np.column_stack([np.zeros(n), np.zeros(n), depth * 1e3]),
        "contact_loc": np.tile([-5e-3, 0.0, -9e-3], (n, 1)),
        "tip_pos": np.tile([0.4, 0.0, 0.2], (n, 1)),
        "depth": depth,
        "phase": np.zeros(n),
        "joint_angles": np.zeros((n, 7)),
        "time": trajectory_id * 600.0 + np.arange(n, dtype=float),
        "trajectory_id": np.full(n, trajectory_id, dtype=np.int64),
        "indenter_type": np.full(n, 1, dtype=np.int64),
        "fe_force": np.column_stack([np.zeros(n), np.zeros(n), depth * 1e3]),
        "fe_pressure": np.full(n, 4000.0),
        "fe_converged": np.ones(n, dtype=bool),
        "nodal_res": np.zeros((n, len(VERTICES), 3)),
    }
    meta = {
        "trajectory_id": trajectory_id,
        "indenter_type": 1,
        "arm": 0,
        "angle": 0.0,
        "azimuth": 0.0,
        "point": [-5e-3, 0.0, -9e-3],
        "direction": [0.0, 0.0, 1.0],
        "rotation": np.eye(3),
        "touch_point": [-5e-3, 0.0, -9e-3],
        "complete": True,
        "message": "",
        "tool_tip": np.eye(4),
        "registration": np.eye(4),
        "sensor_in_biotac": np.eye(4),
    }
    raw = {
        "time": trajectory_id * 600.0 + np.linspace(0, n, m),
        "joints": np.zeros((m, 7)),
        "wrench": np.zeros((m, 6)),
        "electrodes": np.full((m, 19), 2000.0),
        "pdc": np.full(m, 2000.0),
        "depth_command": np.linspace(0, 0.3e-3, m),
        "increment": np.arange(m) - 1,
    }
    arrays = {f"row_{k}": np.asarray(x) for k, x in rows.items()}
    arrays |= {f"meta_{k}": np.asarray(x) for k, x in meta.items()}
    arrays |= {f"raw_{k}": np.asarray(x) for k, x in raw.items()}
    arrays["mesh_reference"] = VERTICES
    return arrays


def write_fake_parts(parts_dir: Path, sensor_id: int = 2, trajectories: int = 2) -> list[Path]:
    """Fake parts of trajectories 0..trajectories-1 where a campaign keeps them."""
    paths = [part_path(parts_dir, sensor_id, tid) for tid in range(trajectories)]
    for tid, path in enumerate(paths):
        write_part(path, fake_part(tid))
    return paths


def write_fake_campaign(folder: Path, sensor_id: int = 2) -> Path:
    """`folder/biotac<id>.hdf5` assembled from two fake parts by the campaign's own assembler (mesh 3 mm)."""
    parts = write_fake_parts(folder / "parts", sensor_id)
    out = folder / f"biotac{sensor_id}.hdf5"
    provenance = {"config": {"mesh_max_edge": 3e-3}}
    assemble_sensor_file(parts, out, sensor_id, list(INDENTERS), provenance, SKIN.faces, VERTICES[:, 2] < 0)
    return out
