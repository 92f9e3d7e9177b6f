"""Pose-driven indentation of B trajectories at once: the batched counterpart of `fe.indentation.IndentationStepper`.

`BatchedStepper.step(rotations, translations, active)` moves each active system's indenter to its pose and
re-solves all of them together on the warp device, with the per-system logic of the single stepper: a
pose that does not touch the free skin costs no Newton work, leaving contact releases to the inflated
state, the warm start extrapolates the last increment and pushes vertices out of the indenter, the
friction slip is measured from stick anchors that persist across increments, and a system whose step
fails refuses further steps until `reset`. Poses: rotation (3,3) indenter body -> sensor frame, tip position
(3,) m; results are `fe.results.IncrementResult`s (forces in N, sensor frame), `wall_s` being the whole batch
step's time.

The step is built from two calls that also serve continuous batching (`fe.batched_runner`): `admit`
starts new increments for some systems while others are mid-solve, and `advance` runs one Newton
iteration of every running system and reports those that finished, so a system never waits for the
slowest one of the batch.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence

import numpy as np
import warp as wp
from scipy.spatial.transform import Rotation, Slerp

from assets.indenters import Indenter, get_indenter
from fe.batched import BatchedShell, InflatedSkin, NewtonBatch, get_rows, put_rows
from fe.indenter_sdf import head_radius
from fe.results import IncrementResult
from fe.shell import pressed_areas
from fe.viscoelastic import SkinRelaxation

MAX_CUTS = 3
"""How often a failed step is halved before it ends a trajectory (`fe.indentation.IndentationStepper`,
`fe.batched_runner.run_trajectories`)."""


Pose = tuple[np.ndarray, np.ndarray, float | None]
"""An indenter pose and its time: rotation (3,3) body -> sensor frame, tip position (3,) m, time (s; None: untimed)."""


def pose_midpoint(start: Pose, end: Pose) -> Pose:
    """Halfway between two timed indenter poses: the rotations' geodesic midpoint, the tips' mean, and the
    mean time (None when either is untimed)."""
    rotations = Rotation.from_matrix(np.stack([start[0], end[0]]))
    rotation = Slerp([0.0, 1.0], rotations)(0.5).as_matrix()
    time_s = None if start[2] is None or end[2] is None else 0.5 * (start[2] + end[2])
    return rotation, 0.5 * (np.asarray(start[1]) + np.asarray(end[1])), time_s


@dataclasses.dataclass
class CutBack:
    """One system's way to its next target pose after failures: a failed increment is undone and taken again
    from the last accepted pose through the midpoint (in pose and time), whose result is not the target's,
    up to `max_cuts` halvings of the step to one target (`fe.indentation.IndentationStepper.step`,
    `fe.batched_runner.run_trajectories`)."""

    max_cuts: int = MAX_CUTS
    detours: list[Pose] = dataclasses.field(default_factory=list)
    """Intermediate poses still to reach, nearest first, before the target."""
    cuts: int = 0
    """Halvings of the step to the current target so far."""
    total: int = 0
    """Halvings over every target since this object was made."""

    def pose(self, target: Pose) -> Pose:
        """The pose to step to next on the way to `target`."""
        return self.detours[0] if self.detours else target

    def settle(self, stepper: BatchedStepper, system: int, converged: bool, target: Pose) -> bool:
        """After `system` of `stepper` finished an increment to `self.pose(target)`: True when that was the
        target's result (reached, or failed for good: the caller reports it); False when the system is to step
        to `self.pose(target)` again (a detour reached, or the failed step undone and halved)."""
        # A step refused as too large before any solve is halved without using up the cuts: its pieces
        # shrink with each halving until one is taken (cut-backs must be on, max_cuts > 0).
        too_large = self.max_cuts > 0 and bool(stepper.too_large[system])
        if not converged and (self.cuts < self.max_cuts or too_large) and stepper.can_retreat(system):
            rotation, translation = stepper.retreat(system)
            end = self.pose(target)
            start_time = None if end[2] is None else float(np.nan_to_num(stepper.time_s[system]))
            self.detours.insert(0, pose_midpoint((rotation, translation, start_time), end))
            self.cuts += 0 if too_large else 1
            self.total += 1
            return False
        if converged and self.detours:
            self.detours.pop(0)
            return False
        self.cuts = 0
        return True

    def restart(self) -> None:
        """Forget the detours and halvings of the current target (a new trajectory), keeping `total`."""
        self.detours, self.cuts = [], 0


_BALANCE_TOLERANCE = 1e-4
"""Largest relative force-balance error of an admissible increment (converged ones show 1e-12 ... 1e-8)."""
_LOAD_FLOOR = 1e-3
"""Indenter force (N) below which neither the force balance nor the force's direction is judged: the balance's
relative error has no scale (a closed balloon's pressure forces sum to zero), and a skin leaving the indenter
ends an unloading at a force of Newton's tolerance (nN) whose direction is noise."""
_PULL_TOLERANCE = 0.1
"""An increment whose indenter force (above `_LOAD_FLOOR`) along the press is below -0.1 |F| pulls the indenter in:
inadmissible (friction tilts a pressing force, but never turns it around)."""


def _check_poses(
    rotation: np.ndarray, translation: np.ndarray, batch: int, active: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Copies of B poses, rotations (B,3,3) and tip positions (B,3) m; the active ones must be proper
    rotations and finite (inactive rows are ignored)."""
    rotation = np.array(rotation, dtype=np.float64)
    translation = np.array(translation, dtype=np.float64)
    if rotation.shape != (batch, 3, 3) or translation.shape != (batch, 3):
        raise ValueError(f"poses are rotations ({batch},3,3) and translations ({batch},3)")
    rot, trans = rotation[active], translation[active]
    if not (np.all(np.isfinite(rot)) and np.all(np.isfinite(trans))):
        raise ValueError("indenter poses have non-finite entries")
    gram = np.einsum("bji,bjk->bik", rot, rot)
    if not np.allclose(gram, np.eye(3), atol=1e-8) or np.any(np.linalg.det(rot) < 0):
        raise ValueError("indenter rotations must be orthonormal with determinant +1")
    return rotation, translation


class BatchedStepper:
    """B independent indentation trajectories, stepped together on `device`.

    `skin`: the inflated model of every system, or one per system (`fe.batched.per_system`: one mesh, each
    with its own parameters and starting state); `indenters`: one indenter (or name) per system; `forcing`,
    `linear` and `later`: the CG tolerance rule, the linear algebra and the skins systems may take later
    (`set_skin`) of `fe.batched.BatchedShell`.
    """

    def __init__(
        self,
        skin: InflatedSkin | Sequence[InflatedSkin],
        indenters: Sequence[str | Indenter],
        device: str = "cpu",
        forcing: str = "adaptive",
        linear: str = "auto",
        later: Sequence[InflatedSkin] = (),
    ) -> None:
        shapes = [get_indenter(name) if isinstance(name, str) else name for name in indenters]
        if not shapes:
            raise ValueError("a batch needs at least one trajectory")
        self.batch = len(shapes)
        self.indenters = [shape.name for shape in shapes]
        indenters = [(s.kind, s.dims) for s in shapes]
        self.shell = BatchedShell(skin, indenters, device, forcing=forcing, linear=linear, later=later)
        self.skins, self.skin = self.shell.skins, self.shell.skin
        skin = self.skin
        B, V = self.batch, len(skin.vertices)
        self.reference = np.zeros((B, V, 3))
        """(B,V,3) starting (inflated) positions (m) of each system."""
        self.reference_pressure, self.rest_volumes = np.zeros(B), np.zeros(B)
        """(B,) starting pressure (Pa) of each system, and the volume (m^3) its starting state encloses
        (liquid + air)."""
        self._rest_residual, self._rest_balance = np.zeros(B), np.zeros(B)
        self._reference_w = wp.zeros((B, V), dtype=wp.vec3d, device=device)
        self.x = np.zeros((B, V, 3))
        """(B,V,3) skin mid-surface positions (m) of the last accepted state."""
        self.pressure = np.zeros(B)
        self.pose_rotation, self.pose_translation = np.tile(np.eye(3), (B, 1, 1)), np.zeros((B, 3))
        self._start_rotation, self._start_translation = self.pose_rotation.copy(), self.pose_translation.copy()
        self._was_posed = np.zeros(B, dtype=bool)
        self.posed = np.zeros(B, dtype=bool)
        """Whether a system has been stepped since its reset (its pose is the start of the next increment)."""
        self.origin, self.has_origin = np.zeros((B, 3)), np.zeros(B, dtype=bool)
        self.failure: list[str | None] = [None] * B
        self.in_contact = np.zeros(B, dtype=bool)
        self._motion, self._has_motion, self._travel = np.zeros((B, V, 3)), np.zeros(B, dtype=bool), np.zeros((B, 3))
        self._gap, self._gap_change = np.zeros((B, V)), np.zeros((B, V))
        self._lagged, self._lagged_change = np.zeros((B, V)), np.zeros((B, V))
        self._anchor, self._anchored = np.zeros((B, V, 3)), np.zeros((B, V), dtype=bool)
        """(B,V,3) where each skin vertex sticks on the indenter, in its body frame (m), and whether it has such a
        stick anchor (pressed with friction at its last equilibrium); `_stick`."""
        self.newton = NewtonBatch.idle(B, 0.0)
        """Newton state of the increments under way (`running` marks the systems mid-solve); with trapped air
        the held volume is the liquid's."""
        self.relaxation = SkinRelaxation(self.shell, np.zeros(B), np.ones(B)) if self.shell.relaxes else None
        self.time_s = np.full(B, np.nan)
        """Time (s) of each system's last step (NaN: none since its reset, or untimed)."""
        self._time_start, self._dt = np.full(B, np.nan), np.zeros(B)
        self._depth, self._admitted_at = np.zeros(B), np.zeros(B)
        self._increment_travel = np.zeros((B, 3))
        self._half, self._core_floor, self._skin_floor = np.zeros(B), np.zeros(B), np.zeros(B)
        """(B,) half-layer (m) of each skin on the indenter's side (0: a zero-thickness membrane); nearest
        approach (m) of the rigid indenter to the rigid core that a converged state may show (both half-layers
        between them at `ContactSettings.min_stretch`); smallest indenter SDF (m) at any point of the skin's
        mid-surface that a converged state may show: the half-layer at `ContactSettings.min_stretch`, or, for a
        zero-thickness skin, `max_penetration` of the thickness inside the body."""
        self._skin_spacing = np.zeros(B)
        """(B,) node spacing (m) of the skin triangles' sampling in that check: half the margin it tests."""
        self.too_large = np.zeros(B, dtype=bool)
        """Whether each system's last increment was refused as too large a step, before any solve."""
        self._core_parts = None
        """Per core triangle, how many pieces each of its edges is split into for the rigid-against-rigid check
        (nodes half the smallest floor apart or closer; None: no core, or no layer between it and the
        indenter)."""
        self._adopt(np.arange(B))

    def _adopt(self, rows: np.ndarray) -> None:
        """Install the skins of systems `rows` (`self.skins`): their starting states, the volumes those hold,
        relaxation branches and admissibility floors, and put them in those states."""
        skins, shell, settings = [self.skins[i] for i in rows], self.shell, self.skin.contact
        self.reference[rows] = np.stack([s.reference for s in skins])
        self.reference_pressure[rows] = [s.pressure for s in skins]
        put_rows(self._reference_w, rows, self.reference[rows])
        put_rows(shell.x, rows, self.reference[rows])
        shell.move_away(rows)  # the starting state's figures without contact
        p_rest, which = self.reference_pressure, np.isin(np.arange(self.batch), rows)
        rest = shell.evaluate(self._reference_w, False, p_rest, which)
        air = shell.air.volume(p_rest)
        self.rest_volumes[rows] = (rest.volume + air)[rows]
        self._rest_residual[rows] = rest.residual_inf[rows]
        self._rest_balance[rows] = self._force_balance(rows, p_rest[rows])[1]
        self.newton.target[rows] = np.array([s.target_volume for s in skins]) - air[rows]
        if self.relaxation is not None:
            fractions = np.array([s.params.relaxation_fraction for s in skins])
            self.relaxation.fractions[rows], self.relaxation.long_term[rows] = fractions, 1.0 - fractions
            self.relaxation.times[rows] = [s.params.relaxation_time_s for s in skins]
        self._half[rows] = [s.indenter_half_layer for s in skins]
        self._core_floor[rows] = settings.min_stretch * (self._half[rows] + self.skin.core_offset)
        thickness = np.array([s.params.thickness for s in skins])
        penetration = settings.max_penetration * thickness
        half = self._half[rows]
        self._skin_floor[rows] = np.where(half > 0.0, settings.min_stretch * half, -penetration)
        self._skin_spacing[rows] = 0.5 * np.where(half > 0.0, self._skin_floor[rows], penetration)
        spacing = 0.5 * self._core_floor.min()
        if shell.has_core and spacing > 0.0:
            corners = self.skin.core_vertices[self.skin.core_triangles]
            longest = np.linalg.norm(corners - np.roll(corners, 1, axis=1), axis=2).max(axis=1)
            parts = np.maximum(np.ceil(longest / spacing), 1).astype(np.int32)
            self._core_parts = wp.array(parts, dtype=wp.int32, device=shell.device)
        self.reset(np.isin(np.arange(self.batch), rows))

    def set_skin(self, system: int, skin: InflatedSkin) -> None:
        """Give one system another skin of the batch's mesh (`fe.batched.BatchedShell.set_skin`); it starts from
        that skin's inflated state (reset it first)."""
        if self.posed[system] or self.newton.running[system]:
            raise RuntimeError(f"reset() system {system} before changing its skin")
        self.shell.set_skin(system, skin)
        self._adopt(np.array([system]))

    # -- state -------------------------------------------------------------------------------------
    def reset(self, which: np.ndarray | None = None) -> None:
        """Back to the inflated state, indenter released and depth origin cleared, for `which` systems (all);
        an increment under way for them is abandoned."""
        which = np.ones(self.batch, dtype=bool) if which is None else np.asarray(which, dtype=bool)
        self.posed[which] = self.has_origin[which] = False
        self.newton.running[which] = False
        for i in np.flatnonzero(which):
            self.failure[i] = None
        self._release(which)
        self.time_s[which] = np.nan
        if self.relaxation is not None:
            rows = np.flatnonzero(which)
            self.relaxation.reset(rows, self.x[rows])

    def _release(self, which: np.ndarray) -> None:
        """Put the systems in `which` back to the inflated state, keeping their poses and depth origins."""
        self.x[which] = self.reference[which]
        self.pressure[which] = self.reference_pressure[which]
        self.in_contact[which] = self._has_motion[which] = self._anchored[which] = False
        self._travel[which] = self._gap[which] = self._gap_change[which] = self._lagged[which] = 0.0

    def set_indenter(self, system: int, name: str) -> None:
        """Change one system's indenter (reset it first: the new one starts from the inflated state)."""
        if self.posed[system] or self.newton.running[system]:
            raise RuntimeError(f"reset() system {system} before changing its indenter")
        shape = get_indenter(name)
        self.shell.set_indenter(system, shape.kind, shape.dims)
        self.indenters[system] = name

    def can_retreat(self, system: int) -> bool:
        """Whether `system` failed an increment that started from an earlier pose (one to step back to)."""
        return self.failure[system] is not None and bool(self._was_posed[system])

    def retreat(self, system: int) -> tuple[np.ndarray, np.ndarray]:
        """Undo a failed increment of `system`: back to its last accepted state and pose, ready to step again
        (e.g. in smaller steps). Returns that pose: rotation (3,3) and tip position (3,) m."""
        if not self.can_retreat(system):
            raise RuntimeError(f"system {system} has no failed increment from an earlier pose to undo")
        self.failure[system] = None
        self.time_s[system] = self._time_start[system]
        self.pose_rotation[system] = self._start_rotation[system]
        self.pose_translation[system] = self._start_translation[system]
        self.posed[system] = self._was_posed[system]
        return self.pose_rotation[system].copy(), self.pose_translation[system].copy()

    # -- stepping ----------------------------------------------------------------------------------
    def step(
        self,
        rotation: np.ndarray,
        translation: np.ndarray,
        active: np.ndarray | None = None,
        times: np.ndarray | None = None,
    ) -> list[IncrementResult | None]:
        """Move each active system's indenter to its pose (B,3,3), (B,3) m at its time (B,) s (see `admit`) and
        re-solve; None for inactive ones."""
        start = time.perf_counter()
        active = np.ones(self.batch, dtype=bool) if active is None else np.asarray(active, dtype=bool)
        if np.any(self.newton.running):
            raise RuntimeError("systems are mid-increment (admitted but not finished); advance() them first")
        done = self.admit(active, rotation, translation, times)
        while self.newton.running.any():
            done |= self.advance()
        wall = time.perf_counter() - start
        return [dataclasses.replace(done[i], wall_s=wall) if i in done else None for i in range(self.batch)]

    def admit(
        self, which: np.ndarray, rotation: np.ndarray, translation: np.ndarray, times: np.ndarray | None = None
    ) -> dict[int, IncrementResult]:
        """Move the indenters of the `which` systems (B,) bool to their poses (rows of (B,3,3), (B,3) m; other
        rows ignored) at their `times` (B,) s (any clock, non-decreasing per system; None: no time passes,
        only for a skin without viscoelastic relaxation) and start their increments. Returns the results of
        those whose pose needs no solve (no contact, nothing creeping); the others are solved by `advance`,
        which the systems mid-increment need not wait for."""
        start = time.perf_counter()
        which = np.asarray(which, dtype=bool).copy()
        failed = [i for i in np.flatnonzero(which) if self.failure[i] is not None]
        if failed:
            raise RuntimeError(f"systems {failed} did not converge last step; reset() them before stepping again")
        if np.any(which & self.newton.running):
            raise RuntimeError(f"systems {np.flatnonzero(which & self.newton.running)} are mid-increment")
        rotation, translation = _check_poses(rotation, translation, self.batch, which)
        self.too_large[which] = False
        self._dt[which] = self._clock(which, times)[which]
        new_origin = which & ~self.has_origin
        self.origin[new_origin] = translation[new_origin]
        self.has_origin |= new_origin
        moved = which & self.posed
        self._was_posed[which] = self.posed[which]
        self._start_rotation[which] = np.where(moved[:, None, None], self.pose_rotation, rotation)[which]
        self._start_translation[which] = np.where(moved[:, None], self.pose_translation, translation)[which]
        self.pose_rotation[which], self.pose_translation[which] = rotation[which], translation[which]
        self.posed |= which
        depth = np.einsum("bi,bi->b", self.origin - translation, rotation[:, :, 2])
        self._depth[which] = depth[which]
        shell, rows = self.shell, np.flatnonzero(which)
        shell.set_poses(self.pose_rotation, self.pose_translation, self._start_rotation, self._start_translation)
        put_rows(shell.x_trial, rows, self.x[rows])
        free_now, free_ref = np.zeros(self.batch, dtype=bool), np.zeros(self.batch, dtype=bool)
        free_now[rows], pressed = self._sweep(rows)
        gap_ref, _, face_ref, _ = shell.proximity(self._reference_w, rows)
        free_ref[rows] = (gap_ref.min(axis=1) >= 0.0) & (face_ref >= 0.0)
        relaxed, memory = np.ones(self.batch, dtype=bool), np.zeros(self.batch, dtype=bool)
        if self.relaxation is not None:
            relaxed[rows], memory = self.relaxation.at_rest(rows), self.relaxation.fractions > 0.0
        untouched = which & free_now & ~self.in_contact & relaxed
        # A skin without viscoelastic memory that the indenter leaves releases to the inflated equilibrium
        # (whatever its batch's neighbours); one with memory creeps back instead, which the solve follows.
        released = which & free_now & self.in_contact & free_ref & ~memory
        self._release(released)
        solving = which & ~untouched & ~released
        refused = {}
        for k in np.flatnonzero(solving[rows]):
            i, half = int(rows[k]), self._half[rows[k]]
            if half > 0.0 and pressed[k] > half:
                message = (
                    f"inadmissible: step too large: the indenter's surface moves {pressed[k] * 1e3:.2f} mm "
                    f"against the skin in one increment (limit: the half-thickness, {half * 1e3:.2f} mm)"
                )
                self.failure[i], solving[i], self.too_large[i] = message, False, True
                refused[i] = self._free_result(i, float(depth[i]), message)
        if self.relaxation is not None and solving.any():
            self.relaxation.prepare(np.flatnonzero(solving), self._dt[solving])
        if solving.any():
            travel = translation - self._start_translation
            self._increment_travel[solving] = travel[solving]
            self._admitted_at[solving] = start
            self._begin(solving, self._predict(np.flatnonzero(solving), travel[solving]))  # warm-started
        free = {int(i): self._free_result(int(i), float(depth[i])) for i in np.flatnonzero(untouched | released)}
        return free | refused

    def _sweep(self, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Whether the skin of systems `rows` at its last state (in the shell's `x_trial`) stays clear of the
        indenter along the whole move from its start pose to its new one ((k,) bool), and how far (m) the
        indenter's surface moves against that skin ((k,)): summed over the sweep's pieces, the largest change
        of the gap of a skin vertex or of a quadrature point of the surface contact (`BatchedShell.proximity`)
        among those touching at either end of the piece. Poses are sampled (rotations
        by slerp, tips on the line) every half-thickness or less of the travel bound |dt| + |dtheta| r_head
        (`fe.indenter_sdf.head_radius`), so the skin is not passed unseen between samples; the shell's poses
        are left at the new ones."""
        shell = self.shell
        start_r, start_t = self._start_rotation[rows], self._start_translation[rows]
        turn = Rotation.from_matrix(self.pose_rotation[rows] @ np.transpose(start_r, (0, 2, 1))).as_rotvec()
        shift = self.pose_translation[rows] - start_t
        radius = np.array([head_radius(*shell.indenters[i]) for i in rows])
        bound = np.linalg.norm(shift, axis=1) + np.linalg.norm(turn, axis=1) * radius
        spacing = np.where(self._half[rows] > 0.0, self._half[rows], np.inf)
        pieces = np.maximum(np.ceil(bound / spacing), 1).astype(int)
        clear, pressed = np.ones(len(rows), dtype=bool), np.zeros(len(rows))
        rotation, translation = self.pose_rotation.copy(), self.pose_translation.copy()
        # The start pose is needed only to measure a move that could exceed the limit (gap changes <= bound).
        first = 0 if np.any(bound > spacing) else 1
        before = None
        last_rotation, last_translation = rotation.copy(), translation.copy()
        for step in range(first, int(pieces.max()) + 1):
            f = np.minimum(step / pieces, 1.0)
            rotation[rows] = Rotation.from_rotvec(f[:, None] * turn).as_matrix() @ start_r
            translation[rows] = start_t + f[:, None] * shift
            shell.set_poses(rotation, translation, last_rotation, last_translation)
            gap, _, face_gap, face_moved = shell.proximity(shell.x_trial, rows)
            live = (step >= 1) & (step <= pieces)
            clear &= ~live | ((gap.min(axis=1) >= 0.0) & (face_gap >= 0.0))
            if before is not None:
                touching = (gap < 0.0) | (before < 0.0)
                moved = np.where(touching, np.abs(gap - before), 0.0).max(axis=1)
                moved = np.maximum(moved, face_moved)
                pressed += np.where(live, moved, 0.0)
            before = gap
            last_rotation[rows], last_translation[rows] = rotation[rows], translation[rows]
        shell.set_poses(self.pose_rotation, self.pose_translation, self._start_rotation, self._start_translation)
        return clear, pressed

    def _clock(self, which: np.ndarray, times: np.ndarray | None) -> np.ndarray:
        """Time steps (B,) s since each `which` system's last step, validating and recording `times`."""
        if times is None:
            if self.relaxation is not None:
                raise ValueError("a viscoelastic skin (relaxation_fraction > 0) needs the time of every step")
            return np.zeros(self.batch)
        times = np.broadcast_to(np.asarray(times, dtype=np.float64), (self.batch,))
        if not np.all(np.isfinite(times[which])):
            raise ValueError("step times must be finite")
        last = np.where(np.isnan(self.time_s), times, self.time_s)
        back = which & (times < last)
        if back.any():
            i = int(np.flatnonzero(back)[0])
            raise ValueError(f"time {times[i]} s of system {i} goes back from its last step's {self.time_s[i]} s")
        self._time_start[which] = self.time_s[which]
        self.time_s[which] = times[which]
        return np.where(which, times - last, 0.0)

    def advance(self) -> dict[int, IncrementResult]:
        """One round for every system mid-increment: one evaluation each (at its positions or its line-search
        trial), then a convergence check and a new Newton direction where it stands at its positions.
        Returns the results of the systems that finished (converged, or failed: such a system refuses
        further steps until `reset`)."""
        stopped = self.shell.round(self.newton)
        return self._finish(np.flatnonzero(stopped)) if stopped.any() else {}

    def hold_volume(self, target: np.ndarray, which: np.ndarray | None = None) -> tuple[np.ndarray, list[str]]:
        """Re-solve the idle `which` systems (default all) at their current poses holding the volumes `target`
        (B,) m^3 from here on: inflation, by volume control. With trapped air the liquid is held at `target`
        minus the bubble's volume at the current pressure (the bubble then follows Boyle's law). A system that
        converges takes the new equilibrium as its state; one that does not keeps its old state and volume.
        Returns whether each converged ((B,) bool, False for systems not solved) and Newton's messages."""
        which = np.ones(self.batch, dtype=bool) if which is None else np.asarray(which, dtype=bool)
        if np.any(which & self.newton.running):
            raise RuntimeError("systems are mid-increment; advance() them first")
        shell, state, rows = self.shell, self.newton, np.flatnonzero(which)
        held = state.target.copy()
        target = np.broadcast_to(np.asarray(target, dtype=np.float64), (self.batch,))
        state.target[which] = (target - shell.air.volume(self.pressure))[which]
        self._begin(which, self.x[rows])
        while state.running.any():
            shell.round(state)
        converged = which & state.converged
        done = np.flatnonzero(converged)
        if len(done):
            self.x[done], self.pressure[done] = get_rows(shell.x, done), state.pressure[done]
            self._stick(done, self.x[done], get_rows(shell.lagged_force, done))
        state.target[which & ~converged] = held[which & ~converged]
        return converged, list(state.message)

    def _begin(self, which: np.ndarray, start: np.ndarray) -> None:
        """Begin Newton for the `which` systems (at least one) from positions `start` (k,V,3) m, their last
        equilibria being the increment's start (friction slips from the stick anchors, `_stick`, or from the last
        equilibrium where a vertex has none) and their lagged contact forces taken at `start`,
        except that a vertex pressed at both last equilibria (and at `start`) takes its last lagged force changed
        as in the last increment, by the share of the last displacement that `start` repeats (fewer Newton rounds
        after the first refresh, whose jump it shrinks)."""
        shell, rows = self.shell, np.flatnonzero(which)
        rotation, translation = self._start_rotation[rows], self._start_translation[rows, None]
        anchors = self._anchor[rows] @ np.swapaxes(rotation, 1, 2) + translation
        put_rows(shell.x_start, rows, np.where(self._anchored[rows, :, None], anchors, self.x[rows]))
        put_rows(shell.x, rows, start)
        shell.lag_contact(shell.x, which)
        motion, last, change = self._motion[rows], self._lagged[rows], self._lagged_change[rows]
        repeated = np.einsum("bvi,bvi->b", start - self.x[rows], motion)
        share = np.clip(repeated / np.maximum(np.einsum("bvi,bvi->b", motion, motion), 1e-300), 0.0, 1.0)
        lagged = get_rows(shell.lagged_force, rows)
        pressed = self._has_motion[rows, None] & (lagged > 0.0) & (last > 0.0) & (last > change)
        put_rows(shell.lagged_force, rows, np.where(pressed, np.maximum(last + share[:, None] * change, 0.0), lagged))
        shell.begin(self.newton, which, self.pressure)

    def _predict(self, rows: np.ndarray, travel: np.ndarray) -> np.ndarray:
        """Warm starts (k,V,3) m of systems `rows` moving their tips by `travel` (k,3) m: the last increment's
        displacement extrapolated by the share of its tip travel that the new move repeats (at a pose held after
        a held one, where only a viscoelastic skin's creep moves it, by its decay exp(-dt / tau) over the step:
        the creep of one Prony branch slows geometrically, half the Newton rounds of a hold), except that,
        when the move turns (its travel or the indenter's rotation leaves the last increment's line), vertices
        in contact at the last equilibrium stick: carried by the indenter's rigid motion from its start pose to
        its new one (zero slip, where friction holds most of them; far fewer Newton rounds when an env's
        indenter turns, issue 19; a straight press keeps the extrapolation, half the Newton iterations of
        sticking there); then vertices deeper in the indenter than at the last equilibrium pushed out; fixed
        DOFs stay where they are (the solve moves only the free ones, so a moved fixed DOF would stay moved)."""
        last, start = self._travel[rows], self.x[rows] - self._start_translation[rows, None]
        moved = np.einsum("bi,bi->b", last, last)
        along = np.einsum("bi,bi->b", travel, last) / np.maximum(moved, 1e-300)  # 0 without a last move
        creep = np.exp(-self._dt[rows] / self.relaxation.times[rows]) if self.relaxation is not None else 0.0
        held = self._has_motion[rows] & (moved == 0.0) & ~travel.any(axis=1)  # creeping on
        share = np.where(held, creep, np.clip(along, 0, 1))
        x = self.x[rows] + share[:, None, None] * np.where(self._has_motion[rows, None, None], self._motion[rows], 0.0)
        turn = self.pose_rotation[rows] @ np.transpose(self._start_rotation[rows], (0, 2, 1))
        stuck = start @ np.swapaxes(turn, 1, 2) + self.pose_translation[rows, None]
        off_line = np.linalg.norm(travel - along[:, None] * last, axis=1) > 1e-3 * np.linalg.norm(travel, axis=1)
        turns = off_line | (np.abs(turn - np.eye(3)).max(axis=(1, 2)) > 1e-9)
        x = np.where(((self._gap[rows] < 0.0) & turns[:, None])[:, :, None], stuck, x)
        put_rows(self.shell.x_trial, rows, x)
        gap, normal, _, _ = self.shell.proximity(self.shell.x_trial, rows)
        depth = np.minimum(self._gap[rows] + share[:, None] * self._gap_change[rows], 0.0)
        x += np.maximum(depth - gap, 0.0)[:, :, None] * normal
        return np.where(self.shell.fixed, self.x[rows], x)

    def _force_balance(self, rows: np.ndarray, pressure: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The `rows` systems' indenter forces (R, 3) N and relative force-balance errors (R,) of the last
        evaluation, at their pressures (R,) Pa."""
        g = np.stack([get_rows(self.shell.gradients[k], rows) for k in range(3)], axis=1)
        gv, pressure = get_rows(self.shell.buf["volume_gradient"], rows), np.asarray(pressure)[:, None, None]
        residual = g.sum(axis=1) - pressure * gv
        anchors = np.where(self.shell.fixed, residual, 0.0).sum(axis=1)
        f_indenter, f_core, f_pressure = -g[:, 2].sum(axis=1), -g[:, 1].sum(axis=1), pressure[:, 0] * gv.sum(axis=1)
        imbalance = np.linalg.norm(f_indenter + f_core + f_pressure + anchors, axis=1)
        scale = np.maximum(np.linalg.norm(f_indenter, axis=1), np.linalg.norm(f_pressure, axis=1))
        return f_indenter, imbalance / np.maximum(scale, 1e-300)

    def _finish(self, rows: np.ndarray) -> dict[int, IncrementResult]:
        """Accept the converged systems among `rows` as their new states (record the failures) and report
        them, from the evaluation at their final positions (still in the shell's buffers)."""
        shell, state, now = self.shell, self.newton, time.perf_counter()
        x_rows = get_rows(shell.x, rows)
        gap_rows = get_rows(shell.buf["indenter_gap"], rows)
        core_gap_rows = get_rows(shell.buf["core_gap"], rows)
        face_gap_rows = get_rows(shell.buf["indenter_face_gap"], rows).min(axis=1)
        lagged_rows = get_rows(shell.lagged_force, rows)
        finished = np.isin(np.arange(self.batch), rows)
        clearance = np.full(self.batch, np.inf)
        if self._core_parts is not None:
            clearance = shell.indenter_clearance(self._core_parts, self._core_floor, finished)
        reach = shell.indenter_skin_clearance(shell.x, self._skin_spacing, self._skin_floor, finished & state.converged)
        forces, balances = self._force_balance(rows, state.pressure[rows])
        contact_areas = pressed_areas(x_rows, gap_rows < 0.0, self.skin.triangles)
        results = {}
        for k, i in enumerate(int(r) for r in rows):
            x, gap, force, balance = x_rows[k], gap_rows[k], forces[k], float(balances[k])
            in_contact = gap < 0.0
            refused = (
                self._inadmissible(i, gap, core_gap_rows[k], (clearance[i], reach[i]), force, balance)
                if state.converged[i]
                else ""
            )
            if refused:
                state.converged[i], state.message[i] = False, f"inadmissible: {refused}"
            if state.converged[i]:
                self._motion[i] = x - self.x[i]
                self._has_motion[i] = True
                self._lagged_change[i], self._lagged[i] = lagged_rows[k] - self._lagged[i], lagged_rows[k]
                self._travel[i] = self._increment_travel[i]
                self._gap_change[i] = np.minimum(gap, 0.0) - np.minimum(self._gap[i], 0.0)
                self._gap[i] = gap
                self.x[i], self.pressure[i] = x, state.pressure[i]
                self.in_contact[i] = in_contact.any() or face_gap_rows[k] < 0.0
                if self.relaxation is not None:
                    self.relaxation.advance(np.array([i]), self._dt[i : i + 1], x[None])
            else:
                self.failure[i] = state.message[i]
            results[i] = self._increment_result(i, x, gap, contact_areas[k], force, balance, now)
        if (accepted := state.converged[rows]).any():
            self._stick(rows[accepted], x_rows[accepted], lagged_rows[accepted])
        return results

    def _stick(self, rows: np.ndarray, x: np.ndarray, lagged: np.ndarray) -> None:
        """Return mapping of the friction (issue 17): after the `rows` systems converged at positions x (k,V,3) m
        with lagged normal forces `lagged` (k,V) N, each pressed vertex keeps a stick anchor on the indenter
        (body frame) where its tangential slip from the anchor is what it was, clipped to the slip length eps:
        a sticking vertex keeps its friction force at a held pose instead of starting the next increment
        unloaded and creeping, a sliding one carries mu lambda on. Vertices without friction force lose theirs."""
        start_r, start_t = self._start_rotation[rows], self._start_translation[rows, None]
        body = (x - self.pose_translation[rows, None]) @ self.pose_rotation[rows]
        slip = body @ np.swapaxes(start_r, 1, 2) + start_t - get_rows(self.shell.x_start, rows)
        normal = get_rows(self.shell.lagged_normal, rows)
        tangential = slip - np.einsum("bvi,bvi->bv", slip, normal)[:, :, None] * normal
        length = np.linalg.norm(tangential, axis=2, keepdims=True)
        kept = tangential * np.minimum(1.0, self.skin.contact.slip_length / np.maximum(length, 1e-300))
        self._anchor[rows] = body - kept @ start_r
        self._anchored[rows] = lagged * np.array([self.skins[i].params.friction for i in rows])[:, None] > 0.0

    def _inadmissible(
        self,
        i: int,
        gap: np.ndarray,
        core_gap: np.ndarray,
        clearances: tuple[float, np.ndarray],
        force: np.ndarray,
        balance: float,
    ) -> str:
        """Why system i's converged state is not a solution of the skin ("" if it is): a half-layer squeezed
        below `ContactSettings.min_stretch` by the indenter or the core (gaps (V,) m, negative closing;
        clamped vertices included for the indenter: on the rim it squeezes the skin onto the rigid base), or
        a zero-thickness contact penetrated deeper than `ContactSettings.max_penetration` of the thickness;
        forces out of balance under a load; or the indenter force pulling the indenter into the skin (it went
        through: force (3,) N on the skin, the press direction being the indenter's -z axis); or the rigid
        indenter nearer the rigid core than both half-layers at the floor allow (`clearance`, m, from
        `fe.batched.BatchedShell.indenter_clearance`): it reached the core through the skin, between skin
        vertices (issue 17 review F2); or the indenter body deeper in a skin triangle, anywhere on it, than the
        layer law allows (`reach` (T,), m, its SDF's minimum over each mid-surface triangle from
        `fe.batched.BatchedShell.indenter_skin_clearance`): below `min_stretch` of the half-layer, or deeper
        than `max_penetration` of the thickness into a zero-thickness contact; it passed between the
        quadrature points (`clearances` = (clearance, reach)). Core gaps of vertices whose search was skipped
        are lower bounds >= 0 (`fe.contact.core_contact_kernel`), so they never refuse."""
        settings, skin = self.skin.contact, self.skins[i]
        free = ~self.shell.fixed.all(axis=1)  # clamped vertices sit on the rigid base: no core contact there
        bodies = [("the indenter", gap, self._half[i])]
        if self.shell.has_core:
            bodies.append(("the core", np.where(free, core_gap, np.inf), skin.core_offset))
        for where, gaps, h in bodies:
            vertex = int(np.argmin(gaps))
            closing = -float(gaps[vertex])
            clamped = " at a clamped vertex (the rigid base)" if np.all(self.shell.fixed[vertex]) else ""
            if h > 0.0 and closing > (1.0 - settings.min_stretch) * h:
                stretch = 1.0 - closing / h
                return (
                    f"{where} squeezes the skin to {stretch:.2f} of its half-thickness{clamped} "
                    f"(floor {settings.min_stretch:.2f})"
                )
            limit = settings.max_penetration * skin.params.thickness
            if h <= 0.0 and closing > limit:
                return f"{where} {closing * 1e6:.0f} um into the skin{clamped} (limit {limit * 1e6:.0f} um)"
        clearance, reach = clearances
        face = int(np.argmin(reach))
        if reach[face] < self._skin_floor[i]:
            law = f"{settings.min_stretch:.2f} of the half-layer" if self._half[i] > 0.0 else "the penetration limit"
            rim = self.shell.fixed[self.skin.triangles[face]].all(axis=1).any()
            clamped = " with a clamped vertex (the rigid base)" if rim else ""
            return (
                f"the indenter reaches into a skin triangle{clamped} ({reach[face] * 1e6:.0f} um from its "
                f"mid-surface; floor {self._skin_floor[i] * 1e6:.0f} um, {law})"
            )
        floor = self._core_floor[i]
        if clearance < floor:
            return (
                f"the indenter reached the core through the skin ({clearance * 1e3:.2f} mm from it; "
                f"floor {floor * 1e3:.2f} mm, both half-layers at {settings.min_stretch:.2f})"
            )
        if np.linalg.norm(force) > _LOAD_FLOOR and not balance <= _BALANCE_TOLERANCE:
            return f"forces out of balance by {balance:.1e} of the load"
        push = float(force @ -self.pose_rotation[i, :, 2])
        if np.linalg.norm(force) > _LOAD_FLOOR and push < -_PULL_TOLERANCE * np.linalg.norm(force):
            return f"the indenter force pulls into the skin ({push:.3g} N along the press)"
        return ""

    def _increment_result(
        self, i: int, x: np.ndarray, gap: np.ndarray, area: float, force: np.ndarray, balance: float, now: float
    ) -> IncrementResult:
        """System i's finished increment: contact radius from its final positions x (V,3) m and indenter gaps (V,)
        m; its contact area (m^2, the lumped areas of the vertices in contact)."""
        state, in_contact = self.newton, gap < 0.0
        axis = self.pose_rotation[i, :, 2]
        rel = x - self.pose_translation[i]
        radial = rel - np.outer(rel @ axis, axis)
        radius = np.linalg.norm(radial, axis=1)[in_contact].max(initial=0.0)
        return IncrementResult(
            depth=float(self._depth[i]),
            force=force,
            pressure=float(state.pressure[i]),
            volume=float(state.volume[i] + self.shell.air.volume(state.pressure[i : i + 1])[0]),
            contact_area=float(area),
            contact_radius=float(radius),
            displacement=x - self.reference[i],
            newton_iterations=int(state.iterations[i]),
            residual=float(state.residual[i]),
            equilibrium_error=balance,
            converged=bool(state.converged[i]),
            message=state.message[i],
            wall_s=now - self._admitted_at[i],
        )

    def _free_result(self, i: int, depth: float, refusal: str = "") -> IncrementResult:
        """System i's increment that needed no solve: free of the indenter at its last state, or refused
        before solving (`refusal`, its reason)."""
        return IncrementResult(
            depth=float(depth),
            force=np.zeros(3),
            pressure=float(self.pressure[i]),
            volume=float(self.rest_volumes[i]),
            contact_area=0.0,
            contact_radius=0.0,
            displacement=self.x[i] - self.reference[i],
            newton_iterations=0,
            residual=float(self._rest_residual[i]),
            equilibrium_error=float(self._rest_balance[i]),
            converged=not refusal,
            message=refusal or "no contact",
            wall_s=0.0,
        )
