"""The FE as the environments see it: many indentation slots stepped through one batched call.

`IndentationBatch.step_batch(rotations, translations)` moves every slot's indenter to its new pose and
returns the skin's answer as stacked arrays (`BatchIncrement`). All slots are the systems of one
`fe.batched_stepper.BatchedStepper` on a warp device (`device`, default "cpu"): one set of kernel
launches per Newton round for the whole batch; the linear algebra follows the device (a sparse direct
factorisation per system on the CPU, batched CG on a GPU: `fe.batched`).

Frames and units: the `biotac` frame of the product manual (x distal, -z ventral), SI (m, N, Pa).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import warp as wp

from fe.batched_stepper import BatchedStepper, CutBack
from fe.results import IncrementResult
from fe.sensor import BioTacModel

COARSE_MESH_MM = 2.0
"""The cheap mesh (largest edge, mm): 281 skin nodes, about 0.05-0.1 s per contact increment on one core."""


def check_device(device: str) -> str:
    """`device` if warp has it here ("cpu", "cuda", "cuda:0", ...); else a one-line ValueError."""
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError) as error:
        raise ValueError(f"warp has no device {device!r} here ({error})") from None
    return device


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
    """`n` independent indentation slots on one inflated FE model, one indenter per slot, solved together
    by one `fe.batched_stepper.BatchedStepper` on the warp `device` ("cpu", "cuda", "cuda:0", ...).

    Every slot starts at the inflated state with its indenter away; `reset(slots)` puts slots back
    there. A slot's failed increment is undone and retaken through halved steps (`fe.batched_stepper.CutBack`,
    up to `MAX_CUTS` halvings) as the one-system `fe.indentation.IndentationStepper` does, so a one-slot
    batch is that stepper.
    """

    def __init__(self, model: BioTacModel, indenters: list[str], device: str = "cpu") -> None:
        if model.reference is None:
            raise ValueError("the FE model must be inflated before it drives an IndentationBatch")
        if not indenters:
            raise ValueError("an IndentationBatch needs at least one slot")
        self.model = model
        self.indenters = list(indenters)
        self.device = check_device(device)
        self._engine = BatchedStepper(model.inflated_skin(), self.indenters, device)
        self.wall_s = 0.0
        """Total wall-clock time (s) spent in `step_batch` so far."""
        self.rounds = 0
        """Newton rounds (one evaluation of every slot still solving, one linear solve) in `step_batch` so far:
        a call takes as many as its slowest slot needs, cut-backs included."""
        self.system_evaluations = 0
        """Slot evaluations in those rounds so far (a round evaluates only the slots still solving)."""

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
        which = np.zeros(self.n, dtype=bool)
        which[range(self.n) if slots is None else [int(k) for k in slots]] = True
        self._engine.reset(which)

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
        results = self._solve(rotations, translations)
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

    def _solve(self, rotations: np.ndarray, translations: np.ndarray) -> list[IncrementResult]:
        """Every slot's result at its target pose, continuously batched: a slot whose increment failed is
        admitted again at once (to the midpoint, then the target) while the others go on iterating, so a
        cut-back costs the call only the rounds of that slot's own detours."""
        engine, targets = self._engine, [(r, t, None) for r, t in zip(rotations, translations, strict=True)]
        plans = [CutBack() for _ in range(self.n)]
        results: list[IncrementResult | None] = [None] * self.n
        evaluations = engine.shell.counters["system_evaluations"]
        again = np.ones(self.n, dtype=bool)
        while again.any() or engine.newton.running.any():
            if again.any():
                poses = [plan.pose(target) for plan, target in zip(plans, targets, strict=True)]
                answers = engine.admit(again, np.array([p[0] for p in poses]), np.array([p[1] for p in poses]))
            else:
                answers = engine.advance()
                self.rounds += 1
            again[:] = False
            for k, answer in answers.items():
                if plans[k].settle(engine, k, answer.converged, targets[k]):
                    results[k] = answer
                else:
                    again[k] = True
        self.system_evaluations += int(engine.shell.counters["system_evaluations"] - evaluations)
        return results
