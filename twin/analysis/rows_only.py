"""Row-only files (the paper's public layout): presses derived from the rows, replayable like a campaign.

The paper's public files hold subsampled rows only: `electrode_vals/data`, the force in `force_vec/data`
(or `force/data`), `contact_loc/data` (m, biotac frame), `indenter_type/data`, maybe `pdc/data`,
`depth/data`, `time/data`, `trajectory_id/data`; no full-rate `raw/` streams and no `trajectories/` group.
This module turns such a file into `CampaignData`:

- presses: successive rows of one indenter whose contact locations follow one press (`segment_presses`);
- each press's direction: the principal axis of its contact locations, pointing into the skin (against
  the nominal skin's outward normal nearest the press); depths: the rows' projections on it, on the grid
  of the step between successive rows, the first row at first contact (depth 0), as in the paper's
  protocol (Methods B), unless the file has `depth/data`; the touch point: the least-squares line origin;
- a stand-in full-rate recording at the protocol's sample rate, each row held over its increment (the
  rows' times, or the protocol's step / speed + pause without `time/data`), so that `Predictor` replays
  the press and processes its prediction exactly as for a campaign file. The stand-in streams are not
  measurements: noise and full-rate effects are not identifiable from them (`RAW_ONLY_EFFECTS`).
"""

from __future__ import annotations

import json
import re
from functools import cache
from pathlib import Path

import h5py
import numpy as np

from assets.biotac import make_biotac, vertex_normals
from assets.indenters import PUBLIC_NAMES, indenter_name
from assets.mount import MountGeometry
from twin.analysis.data import CampaignData, TrajectoryRecord, file_digest
from twin.controller import Recording
from twin.protocol import ProtocolSettings

FORCE_GROUPS = ("force_vec", "force")
"""Where a row-only file keeps the force on the BioTac (N, biotac frame): the public files' group first."""
DEFAULT_MESH = 2e-3
"""FE mesh (m) of the default model for a row-only file (it records none)."""
LOCATION_JUMP = 2e-3
"""A step between successive rows longer than this (m) starts a new press."""
MIN_PRESS_ROWS = 3
"""Presses with fewer rows have no direction and are dropped."""
NORMAL_RADIUS = 1.5e-3
"""Radius (m) over which the nominal skin's normals are averaged for a press's tilt."""
STEP_SNAP = 0.25
"""A median step between rows within this fraction of the protocol's step is taken as the protocol's."""
PROTOCOL = ProtocolSettings()
"""The paper's protocol: step, speed, pause, standoff and sample rate of the stand-in recordings."""
STANDOFF_SAMPLES = 10
"""Stand-in samples before a press's first increment (tare)."""
RAW_ONLY_EFFECTS = {
    "time_delay": "the F/T and joint streams' relative timing is not in the rows",
    "ft_drift": "the tare sample and the full-rate time base are not in the rows",
    "skin_relaxation": "the settle pauses are not recorded, only their last samples",
    "ft_saturation": "the untared F/T readings, whose bias a range clips too, are not in the rows",
}
"""Library effects a row-only file cannot identify, and why (`twin diagnose` does not try them on such files)."""


def is_rows_only(f: h5py.File) -> bool:
    """True for a file with rows (electrodes, force, contact locations) that is not a campaign file (no
    `schema_version` attribute: a campaign file must be complete) and has no replayable recording."""
    has_rows = all(k in f for k in ("electrode_vals", "contact_loc")) and any(k in f for k in FORCE_GROUPS)
    return has_rows and "schema_version" not in f.attrs and not ("raw" in f and "trajectories" in f)


def rows_only_note(path: Path | str) -> str:
    """One line for stderr: the file is read row-only, which effects that leaves unidentifiable, and whether its
    indenter indices were read as the public meshes' order (`indenter_names_of`)."""
    effects = "; ".join(f"{name} ({why})" for name, why in RAW_ONLY_EFFECTS.items())
    with h5py.File(path, "r") as f:
        named = "indenter_names" in f.attrs
    order = "" if named else f"; indenter_type taken as the public meshes in order ({', '.join(PUBLIC_NAMES)})"
    return f"{path}: rows only (no raw streams); presses derived from the rows; not identifiable: {effects}{order}"


def segment_presses(location: np.ndarray, indenter: np.ndarray) -> np.ndarray:
    """(N,) press index of each row from contact locations (N, 3) m and indenter indices (N,).

    A new press starts where the indenter changes, where the location jumps by more than `LOCATION_JUMP`,
    or where, after the press has turned (a step outward along its loading direction longer than half the
    typical step), a step goes inward again by more than half the typical step.
    """
    steps = np.diff(location, axis=0)
    lengths = np.linalg.norm(steps, axis=1)
    half = 0.5 * float(np.median(lengths)) if len(lengths) else 0.0
    press = np.zeros(len(location), dtype=np.int64)
    start, turned, axis = 0, False, None
    for i in range(1, len(location)):
        new = indenter[i] != indenter[i - 1] or lengths[i - 1] > LOCATION_JUMP
        if not new and not turned:
            reach = location[i - 1] - location[start]
            if np.linalg.norm(reach) > half:
                axis = reach / np.linalg.norm(reach)
            turned = axis is not None and float(steps[i - 1] @ axis) < -half
        elif not new:
            new = float(steps[i - 1] @ axis) > half
        if new:
            start, turned, axis = i, False, None
        press[i] = press[i - 1] + int(new)
    return press


@cache
def _nominal_skin() -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) m and outward unit normals (V, 3) of the nominal skin mid-surface (2 mm mesh)."""
    skin = make_biotac(2e-3).skin
    return skin.vertices, vertex_normals(skin.vertices, skin.triangles)


def press_geometry(location: np.ndarray, depth: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(direction (3,) unit, touch point (3,) m, depth (K,) m) of one press from its contact locations
    (K, 3) m; `depth` (K,) m when the file has it, else projections on the step grid (first row at 0): the
    median step between rows, or the protocol's step when that is within `STEP_SNAP` of it."""
    centred = location - location.mean(axis=0)
    direction = np.linalg.svd(centred, full_matrices=False)[2][0]
    vertices, normals = _nominal_skin()
    nearest = np.argmin(np.linalg.norm(vertices - location[0], axis=1))
    if direction @ normals[nearest] > 0.0:
        direction = -direction
    if depth is None:
        along = (location - location[0]) @ direction
        step = float(np.median(np.abs(np.diff(along))))
        if abs(step - PROTOCOL.step) < STEP_SNAP * PROTOCOL.step:
            step = PROTOCOL.step
        depth = np.round(along / step) * step if step > 0 else along
    touch = np.mean(location - np.outer(depth, direction), axis=0)
    return direction, touch, depth


def _angle_to_normal(direction: np.ndarray, touch: np.ndarray) -> float:
    """Tilt (rad) of a press direction from the nominal skin's inward normal near `touch` (vertex normals
    weighted by a Gaussian of `NORMAL_RADIUS`; within about 8 degrees of the inflated skin's on the ventral
    side, as measured on simulated campaigns)."""
    vertices, normals = _nominal_skin()
    weight = np.exp(-((np.linalg.norm(vertices - touch, axis=1) / NORMAL_RADIUS) ** 2))
    normal = weight @ normals
    return float(np.arccos(np.clip(-direction @ normal / np.linalg.norm(normal), -1.0, 1.0)))


def stand_in_recording(rows: dict[str, np.ndarray], sensor_in_biotac: np.ndarray, rate_hz: float) -> Recording:
    """A full-rate stand-in of one press from its rows (see the module docstring), each row the last sample of
    its increment. rows: force (K, 3) N biotac frame, electrode_vals (K, 19), pdc (K,), depth (K,) m,
    time (K,) s (increasing)."""
    times = rows["time"]
    if np.any(np.diff(times) <= 0):
        raise ValueError("row times must increase within a press")
    interval = float(np.median(np.diff(times))) if len(times) > 1 else 1.0
    edges = np.r_[times[0] - interval, times]
    standoff = edges[0] - np.arange(STANDOFF_SAMPLES - 1, -1, -1) / rate_hz
    parts, increments = [standoff], [np.full(STANDOFF_SAMPLES, -1)]
    for k in range(len(times)):
        n = max(1, int(round((edges[k + 1] - edges[k]) * rate_hz)))
        parts.append(edges[k] + (edges[k + 1] - edges[k]) * np.arange(1, n + 1) / n)
        increments.append(np.full(n, k))
    time, increment = np.concatenate(parts), np.concatenate(increments)
    held = np.clip(increment, 0, None)
    standing = increment < 0
    force = np.where(standing[:, None], 0.0, rows["force"][held])
    wrench = np.zeros((len(time), 6))
    wrench[:, :3] = force @ sensor_in_biotac[:3, :3]  # force_biotac = wrench @ R.T
    electrodes = np.where(standing[:, None], 0.0, rows["electrode_vals"][held])
    pdc = np.where(standing, rows["pdc"][0], rows["pdc"][held])
    depth = np.where(standing, min(-PROTOCOL.standoff, float(rows["depth"].min())), rows["depth"][held])
    return Recording(time, np.zeros((len(time), 7)), wrench, electrodes, pdc, depth, increment, True, "")


def indenter_names_of(f: h5py.File, count: int) -> list[str]:
    """Our names of the file's indenter indices: its `indenter_names` attribute (ours or public mesh names),
    else the public meshes in their listed order (assets.indenters.PUBLIC_NAMES)."""
    attr = f.attrs.get("indenter_names")
    names = json.loads(attr) if isinstance(attr, str | bytes) else list(PUBLIC_NAMES)
    if count > len(names):
        raise ValueError(f"indenter_type {count - 1} has no name ({len(names)} known: {names})")
    return [indenter_name(str(n)) for n in names]


def _sensor_id(f: h5py.File, path: Path) -> int:
    if "sensor_id" in f.attrs:
        return int(f.attrs["sensor_id"])
    digits = re.findall(r"\d+", path.stem)
    return int(digits[0]) if digits else 0


def _read_rows(f: h5py.File) -> dict[str, np.ndarray | None]:
    """The file's row features (None where absent), force from the first of `FORCE_GROUPS`."""
    force_group = next(k for k in FORCE_GROUPS if k in f)

    def read(name: str) -> np.ndarray | None:
        return np.asarray(f[f"{name}/data"][()], dtype=float) if name in f else None

    rows = {k: read(k) for k in ("electrode_vals", "contact_loc", "pdc", "depth", "time", "trajectory_id")}
    rows["force"] = read(force_group)
    rows["indenter_type"] = read("indenter_type")
    return rows


def load_rows_only(path: Path | str) -> CampaignData:
    """A row-only file as `CampaignData` whose trajectories are the derived presses (module docstring)."""
    path = Path(path)
    mount = MountGeometry()
    sensor_in_biotac = np.linalg.inv(mount.biotac_in_mount()) @ mount.ft_sensor_in_mount()
    with h5py.File(path, "r") as f:
        rows = _read_rows(f)
        n = len(rows["electrode_vals"])
        indenter = np.zeros(n, int) if rows["indenter_type"] is None else rows["indenter_type"].astype(int).ravel()
        names = indenter_names_of(f, int(indenter.max(initial=0)) + 1)
        sensor_id = _sensor_id(f, path)
    location = rows["contact_loc"]
    boundary = np.diff(segment_presses(location, indenter)) != 0
    if rows["trajectory_id"] is not None:
        boundary |= np.diff(rows["trajectory_id"].ravel()) != 0
    press = np.r_[0, np.cumsum(boundary)]
    records = []
    for index, p in enumerate(np.unique(press)):
        mine = np.flatnonzero(press == p)
        if len(mine) < MIN_PRESS_ROWS:
            continue
        direction, touch, depth = press_geometry(location[mine], None if rows["depth"] is None else rows["depth"][mine])
        electrodes = rows["electrode_vals"][mine]
        press_rows = {
            "force": rows["force"][mine],
            "electrode_vals": electrodes - electrodes[0],
            "pdc": np.full(len(mine), np.nan) if rows["pdc"] is None else rows["pdc"][mine],
            "depth": depth,
            "time": (
                (np.arange(len(mine)) + 1.0) * (PROTOCOL.step / PROTOCOL.speed + PROTOCOL.pause_s)
                if rows["time"] is None
                else rows["time"][mine]
            ),
            "contact_loc": location[mine],
            "trajectory_id": np.full(len(mine), index),
        }
        press_rows["phase"] = (np.arange(len(mine)) > np.argmax(depth)).astype(np.int64)
        raw = stand_in_recording(press_rows, sensor_in_biotac, PROTOCOL.sample_rate_hz)
        rotation = _indenter_rotation(direction)
        records.append(
            TrajectoryRecord(
                sensor_id=sensor_id,
                trajectory_id=index,
                indenter=names[int(indenter[mine[0]])],
                arm="left",
                angle=_angle_to_normal(direction, touch),
                rotation=rotation,
                touch_point=touch,
                direction=direction,
                tool_tip=np.eye(4),
                registration=np.eye(4),
                sensor_in_biotac=sensor_in_biotac,
                complete=True,
                raw=raw,
                rows=press_rows,
                rows_only=True,
            )
        )
    return CampaignData(path, sensor_id, names, records, DEFAULT_MESH, file_digest(path), rows_only=True)


def _indenter_rotation(direction: np.ndarray) -> np.ndarray:
    """(3, 3) indenter frame in the biotac frame pressing along `direction` (the frame's -z), its x axis as
    close to the biotac x axis as the direction allows: the rows do not record the tool's roll, which
    matters for the cylinders and the cube."""
    z = -direction
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - (ref @ z) * z
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])
