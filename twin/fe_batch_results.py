"""The results file of `twin fe batch` (.npz): per trajectory and pose, what the batched FE found.

Arrays (M trajectories, K poses): names (M,); rotations (M,K,3,3) body -> sensor frame and translations
(M,K,3) m, the poses asked for (NaN past a trajectory's last pose); force (M,K,3) N in the sensor frame,
depth (M,K) m, pressure (M,K) Pa, contact_area (M,K) m^2, newton_iterations (M,K), converged (M,K),
loaded (M,K) (in contact: solved, not a free pose); poses_done (M,) and ended (M,) (the trajectory ran
to its end: last pose, force limit or failure). Per-pose values are NaN / 0 / False past poses_done.
options: what made the results beside the poses (the model with its effects and mesh, force limit,
cut-backs, speed), as JSON, so a resume never mixes runs of another model. The file is written atomically,
so a crash leaves the last complete version.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fe.batched_runner import PoseTrajectory
from fe.indentation import IncrementResult

POSES_FILE_KEYS = ("names", "rotations", "translations")
"""Arrays of a poses file (`twin fe batch --poses`; a results file is one too): indenter names (M,),
rotations (M,K,3,3) body -> sensor frame, tip positions (M,K,3) m in the sensor frame."""
_PER_POSE = {"force": (3,), "depth": (), "pressure": (), "contact_area": ()}


class BatchResults:
    """The results arrays of `runs`, filled trajectory by trajectory (`put`) and saved to `out` (`save`)."""

    def __init__(self, out: Path, runs: list[PoseTrajectory], options: dict) -> None:
        """`options`: what else made the results (JSON-ready), checked on `resume`."""
        self.out, self.options = out, options
        m, k = len(runs), max(len(t.translations) for t in runs)
        self.arrays: dict[str, np.ndarray] = {
            "names": np.array([t.indenter for t in runs]),
            "rotations": np.full((m, k, 3, 3), np.nan),
            "translations": np.full((m, k, 3), np.nan),
            **{key: np.full((m, k, *shape), np.nan) for key, shape in _PER_POSE.items()},
            "newton_iterations": np.zeros((m, k), dtype=int),
            "converged": np.zeros((m, k), dtype=bool),
            "loaded": np.zeros((m, k), dtype=bool),
            "poses_done": np.zeros(m, dtype=int),
            "ended": np.zeros(m, dtype=bool),
        }
        for i, t in enumerate(runs):
            self.arrays["rotations"][i, : len(t.rotations)] = t.rotations
            self.arrays["translations"][i, : len(t.translations)] = t.translations

    def resume(self) -> np.ndarray:
        """Take the ended trajectories from an earlier file at `out` for the same poses; returns which
        trajectories (M,) bool still need running. A file for other poses is an error."""
        with np.load(self.out) as data:
            earlier = {key: data[key] for key in data.files}
        same = all(key in earlier and earlier[key].shape == self.arrays[key].shape for key in self.arrays)
        same = same and np.array_equal(earlier["names"], self.arrays["names"])
        for key in ("rotations", "translations"):
            same = same and np.allclose(earlier[key], self.arrays[key], rtol=0.0, atol=1e-12, equal_nan=True)
        if not same:
            raise ValueError(f"{self.out} holds other trajectories; give another --out, or the same options")
        stored = json.loads(str(earlier["options"])) if "options" in earlier else {}
        differ = sorted(k for k in stored.keys() | self.options.keys() if stored.get(k) != self.options.get(k))
        if differ:
            raise ValueError(f"{self.out} was made with other {', '.join(differ)}; give another --out, or the same")
        ended = earlier["ended"]
        for key in self.arrays:
            self.arrays[key][ended] = earlier[key][ended]
        return ~ended

    def put(self, index: int, increments: list[IncrementResult], ended: bool) -> None:
        """Trajectory `index`'s increments, in pose order, and whether it ran to its end."""
        a = self.arrays
        a["poses_done"][index], a["ended"][index] = len(increments), ended
        for j, r in enumerate(increments):
            for key in _PER_POSE:
                a[key][index, j] = getattr(r, key)
            a["newton_iterations"][index, j], a["converged"][index, j] = r.newton_iterations, r.converged
            a["loaded"][index, j] = r.message != "no contact"

    def save(self) -> None:
        """Write the arrays to `out` atomically."""
        self.out.parent.mkdir(parents=True, exist_ok=True)
        partial = self.out.with_name(self.out.name + ".partial.npz")
        np.savez(partial, **self.arrays, options=json.dumps(self.options, sort_keys=True))
        partial.replace(self.out)

    def summary(self) -> dict:
        """Trajectories, how many ended, loaded increments and how many did not converge."""
        a = self.arrays
        return {
            "trajectories": len(a["names"]),
            "ended": int(a["ended"].sum()),
            "loaded_increments": int(a["loaded"].sum()),
            "not_converged": int((a["loaded"] & ~a["converged"]).sum()),
            "out": str(self.out),
        }


def read_poses(path: Path) -> dict[str, np.ndarray]:
    """The arrays of a poses file, checked (`POSES_FILE_KEYS`); a ValueError says what is wrong."""
    if not path.exists():
        raise ValueError(f"no poses file {path}")
    with np.load(path) as data:
        missing = [k for k in POSES_FILE_KEYS if k not in data.files]
        if missing:
            raise ValueError(f"{path} lacks {missing}; a poses file holds {list(POSES_FILE_KEYS)}")
        arrays = {k: np.asarray(data[k]) for k in POSES_FILE_KEYS}
    m = len(arrays["names"])
    rotations, translations = arrays["rotations"], arrays["translations"]
    if m == 0 or rotations.shape[:1] != (m,) or translations.shape[:1] != (m,):
        raise ValueError(f"{path}: names, rotations and translations need the same number (>= 1) of trajectories")
    if rotations.ndim != 4 or rotations.shape[2:] != (3, 3) or translations.shape != rotations.shape[:2] + (3,):
        raise ValueError(
            f"{path}: rotations must be (M,K,3,3) and translations (M,K,3), got {rotations.shape} and "
            f"{translations.shape}"
        )
    return arrays
