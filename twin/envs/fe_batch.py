"""The FE as the environments see it: many indentation slots stepped through one batched call.

`IndentationBatch.step_batch(rotations, translations)` moves every slot's indenter to its new pose and
returns the skin's answer as stacked arrays (`BatchIncrement`). Two backends, the same call:
- `device=None` (default): a plain loop over one `fe.indentation.IndentationStepper` per slot, all on
  one inflated `fe.sensor.BioTacModel` (sparse direct Newton on the CPU);
- `device="cpu"` or `"cuda:0"`: `fe.batched_stepper.BatchedStepper`, all slots in one set of warp
  launches with a batched block-sparse Newton and CG on that device (its docs state its agreement with
  the CPU stepper).

Frames and units: the `biotac` frame of the product manual (x distal, -z ventral), SI (m, N, Pa).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from assets.biotac import make_biotac
from fe.params import SkinParameters
from fe.sensor import BioTacModel
from twin.campaign import inflated_model

COARSE_MESH_MM = 2.0
"""The cheap mesh (largest edge, mm): 281 skin nodes, about 0.05-0.1 s per contact increment on one core."""


@lru_cache(maxsize=4)
def shared_model(mesh_mm: float = COARSE_MESH_MM) -> BioTacModel:
    """An inflated nominal BioTac FE model with `mesh_mm` (mm) largest edges, built once per process."""
    if not 0.3 <= mesh_mm <= 5.0:
        raise ValueError(f"mesh_mm must be in [0.3, 5] mm, got {mesh_mm!r}")
    return inflated_model(make_biotac(mesh_mm * 1e-3), SkinParameters())


@dataclass(frozen=True)
class BatchIncrement:
    """The FE's answer for every slot of one `step_batch` call (SI units, biotac frame)."""

    force: np.ndarray
    """(N, 3) force of the indenter on the skin (N)."""
    pressure: np.ndarray
    """(N,) fluid pressure (Pa)."""
    displacement: np.ndarray
    """(N, V, 3) skin mid-surface nodal displacement from the inflated reference (m)."""
    contact_area: np.ndarray
    """(N,) deformed skin area in contact with the indenter (m^2)."""
    converged: np.ndarray
    """(N,) bool: the slot's solve converged (a slot that failed must be reset before it steps again)."""
    wall_s: float
    """Wall-clock time of the whole call (s)."""


class IndentationBatch:
    """`n` independent indentation slots on one inflated FE model, one indenter per slot.

    Every slot starts at the inflated state with its indenter away; `reset(slots)` puts slots back
    there. `device`: None for the loop of CPU steppers, else the warp device of the batched FE (module
    docstring). Each of the loop's slots is a one-system stepper of the FE engine, so stepping slots in
    turn gives the same answers as stepping them alone.
    """

    def __init__(self, model: BioTacModel, indenters: list[str], device: str | None = None) -> None:
        if model.reference is None:
            raise ValueError("the FE model must be inflated before it drives an IndentationBatch")
        if not indenters:
            raise ValueError("an IndentationBatch needs at least one slot")
        self.model = model
        self.indenters = list(indenters)
        self.device = device
        if device is None:
            self._steppers = [model.stepper(name) for name in self.indenters]
        else:
            from fe.batched import InflatedSkin
            from fe.batched_stepper import BatchedStepper

            self._batched = BatchedStepper(InflatedSkin.from_model(model), self.indenters, device)
        self.wall_s = 0.0
        """Total wall-clock time (s) spent in `step_batch` so far."""

    @property
    def n(self) -> int:
        """Number of slots."""
        return len(self.indenters)

    @property
    def reference(self) -> np.ndarray:
        """(V, 3) inflated skin mid-surface (m)."""
        return self.model.reference

    def reset(self, slots: list[int] | np.ndarray | None = None) -> None:
        """Back to the inflated state with the indenter released, for `slots` (None: all)."""
        chosen = range(self.n) if slots is None else [int(k) for k in slots]
        if self.device is None:
            for k in chosen:
                self._steppers[k].reset()
        else:
            which = np.zeros(self.n, dtype=bool)
            which[list(chosen)] = True
            self._batched.reset(which)

    def step_batch(self, rotations: np.ndarray, translations: np.ndarray) -> BatchIncrement:
        """Move slot k's indenter to (rotations[k] (3,3) body->biotac, translations[k] (3,) tip, m) and
        re-solve every slot (quasi-static, volume held, warm-started from the slot's last state)."""
        rotations = np.asarray(rotations, dtype=float)
        translations = np.asarray(translations, dtype=float)
        if rotations.shape != (self.n, 3, 3) or translations.shape != (self.n, 3):
            raise ValueError(
                f"step_batch needs rotations ({self.n}, 3, 3) and translations ({self.n}, 3), "
                f"got {rotations.shape} and {translations.shape}"
            )
        start = time.perf_counter()
        if self.device is None:
            results = [s.step(r, t) for s, r, t in zip(self._steppers, rotations, translations, strict=True)]
        else:
            results = self._batched.step(rotations, translations)
        wall_s = time.perf_counter() - start
        self.wall_s += wall_s
        return BatchIncrement(
            force=np.array([r.force for r in results]),
            pressure=np.array([r.pressure for r in results]),
            displacement=np.array([r.displacement for r in results]),
            contact_area=np.array([r.contact_area for r in results]),
            converged=np.array([r.converged for r in results]),
            wall_s=wall_s,
        )
