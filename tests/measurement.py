"""A simulated campaign file as a real testbed would write it: without the plant's own fe view."""

from pathlib import Path

import h5py

from twin.dataset import SIMULATION_ONLY


def strip_plant_view(path: Path, out: Path) -> Path:
    """A copy of a campaign file without the plant's fe view (what a real testbed's file would hold)."""
    with h5py.File(path, "r") as src, h5py.File(out, "w") as dst:
        for key, value in src.attrs.items():
            dst.attrs[key] = value
        for name in src:
            if name not in SIMULATION_ONLY:
                src.copy(src[name], dst, name)
    return out
